"""Process-wide tuning, applied once at start by every ``geoloc`` command.

glibc's malloc hands buffers above a *dynamic* threshold straight to mmap and gives them back on free,
so each SIFT pyramid can pay fresh page faults until the threshold happens to adapt, which depends on
what the process did before. Measured on 1600 px penn photos, one thread (as ``geoloc eval``/``ingest``
and the benchmark's floor run), RootSIFT in a fresh process is markedly faster with a fixed 64 MB mmap
threshold; in a thread pool with decoding in between (the server) both settings measured the same: no
gain, no loss. The cost is at most 128 MB of freed memory kept for reuse. ``GEOLOC_MALLOC_TUNING=0`` turns it
off; other C libraries are left alone.

Every setting here is a ``Settings`` field (``malloc_tuning``, ``malloc_trim``, ``blas_threads``) that the
process's start passes in (``configure_allocator``, ``serving_blas_threads``): nothing here reads the
environment, so a test or an embedding program sets them as it sets any other.
"""

from __future__ import annotations

import ctypes
import ctypes.util

M_TRIM_THRESHOLD = -1
M_MMAP_THRESHOLD = -3
MMAP_THRESHOLD_BYTES = 64 << 20
TRIM_THRESHOLD_BYTES = 128 << 20


def configure_allocator(tuning: bool, trim: bool) -> bool:
    """The allocator's settings (``Settings.malloc_tuning``, ``Settings.malloc_trim``), applied once at the
    start of a process (every ``geoloc`` command): the fixed thresholds (``tune_malloc``; returns whether
    glibc accepted them) and whether ``release_free_memory`` hands memory back."""
    global _trim_enabled
    _trim_enabled = trim
    return tune_malloc(tuning)


def tune_malloc(enabled: bool = True) -> bool:
    """True when glibc accepted the fixed thresholds; False when not ``enabled`` or not glibc."""
    if not enabled:
        return False
    name = ctypes.util.find_library("c")
    if not name:
        return False
    try:
        libc = ctypes.CDLL(name)
        mallopt = libc.mallopt
    except (OSError, AttributeError):  # not glibc (musl, macOS): nothing to tune
        return False
    return bool(mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES)) and bool(
        mallopt(M_TRIM_THRESHOLD, TRIM_THRESHOLD_BYTES)
    )


_libc_trim = None
#: Whether ``release_free_memory`` trims (``Settings.malloc_trim``, set by ``configure_allocator``).
_trim_enabled = True


def release_free_memory() -> bool:
    """Hand the allocator's free memory back to the kernel (glibc ``malloc_trim(0)``, all arenas).

    Why: with the thresholds above, a 49 MP decode's buffers come from the per-thread arenas, and glibc
    keeps what they free (up to the 128 MB trim threshold each) after the request, so a few concurrent large
    uploads left RSS far above idle for good (bench/locate_memory.py). Called after large decodes only; it costs a
    walk over the arenas (milliseconds). False where the C library has no malloc_trim, or where the
    process's settings turned it off (``GEOLOC_MALLOC_TRIM=0``, ``configure_allocator``)."""
    global _libc_trim
    if _libc_trim is None:
        name = ctypes.util.find_library("c")
        try:
            _libc_trim = ctypes.CDLL(name).malloc_trim if name else False
        except (OSError, AttributeError):
            _libc_trim = False
    if not _libc_trim or not _trim_enabled:
        return False
    _libc_trim(0)
    return True


#: BLAS threads while serving (``serving_blas_threads``): ``Settings.blas_threads``'s default.
SERVING_BLAS_THREADS = 1


def serving_blas_threads(threads: int = SERVING_BLAS_THREADS) -> int | None:
    """Limit the BLAS library (OpenBLAS under numpy) to ``threads`` (``Settings.blas_threads``: one by default)
    for a process that answers queries; the number of threads set, or None where threadpoolctl found no BLAS
    to limit.

    Why: a query's BLAS work is one vector through the PCA-whitening (a few ms), yet after each parallel
    call OpenBLAS's worker threads spin, busy, for about 2^28 cycles before they sleep, and that spinning
    falls on the next query's SIFT and CNN. Measured on 2 cores (``lite2-hybrid-384``, 1600 px photos, the
    service in-process), one thread cuts both the CPU and the wall time of a /locate markedly (docs/benchmarks.md,
    "A faster default"). A fit has its own fixed count (``fit_threads``)."""
    import numpy  # noqa: F401  (threadpoolctl limits the BLAS libraries already loaded: numpy's)
    from threadpoolctl import threadpool_info, threadpool_limits

    n = max(1, threads)
    threadpool_limits(limits=n, user_api="blas")
    # A process-wide OpenBLAS pool answers (threadpoolctl >= 3.6) only to the thread that set it first;
    # hand that back, so that a fit on another thread (the first start's loader) can raise the limit.
    clear = getattr(_openblas_controller(), "clear_controlling_thread", None)
    if clear is not None:
        clear(force=True)
    # threadpool_info, not the limiter's original counts: those warn when the BLAS libraries loaded (numpy's,
    # scipy's, faiss's) started with different thread counts, on every start of the server.
    return n if any(i["user_api"] == "blas" for i in threadpool_info()) else None


def _openblas_controller():
    import threadpoolctl

    return getattr(threadpoolctl, "OpenBLASController", None)


#: BLAS and OpenMP threads of a fit's numerical steps (``fit_threads``).
FIT_THREADS = 1


def fit_threads():
    """A context in which BLAS (numpy, scipy, faiss) and OpenMP (scikit-learn's k-means, faiss) use
    ``FIT_THREADS`` threads, whatever the machine: the fit's k-means, PCA-whitening, ITQ, SVM bank and
    calibration run inside it.

    Why one thread, on every machine: a parallel reduction sums in an order set by the thread
    count, so the same manifest fitted with 1 and with 2 BLAS threads gave another PCA (another float in the
    last place is enough to move a k-means assignment, a threshold, a ranked id), and the README's demo
    figures differed from one machine to the next. It is also faster where cores are busy: OpenMP's threads
    spin at every one of mini-batch k-means's small parallel steps, and on 2 loaded cores a fit's k-means
    took several times as long with 2 threads as with one (the same centres).
    Feature extraction (onnxruntime, OpenCV) keeps its own threads: it is per image, and gives the same
    features with any count (tests/test_fit_reproducible.py).

    scikit-learn is imported here, before the limit: threadpoolctl limits only the libraries already loaded,
    and the fit's modules import scikit-learn (its OpenMP runtime) only when they fit, so that serving never
    pays for that import."""
    import sklearn.cluster  # noqa: F401  (loads scikit-learn's OpenMP runtime, which the limit must reach)
    from threadpoolctl import threadpool_limits

    return threadpool_limits(limits=FIT_THREADS)

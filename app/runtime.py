"""Process-wide tuning, applied once at start by every ``geoloc`` command.

glibc's malloc hands buffers above a *dynamic* threshold straight to mmap and gives them back on free,
so each SIFT pyramid can pay fresh page faults until the threshold happens to adapt, which depends on
what the process did before. Measured on 1600 px penn photos, one thread (as ``geoloc eval``/``ingest``
and the benchmark's floor run): RootSIFT 70-87 ms in a fresh process, 45-50 ms with a fixed 64 MB mmap
threshold. In a thread pool with decoding in between (the server) both settings measured 53 ms: no gain,
no loss. The cost is at most 128 MB of freed memory kept for reuse. ``GEOLOC_MALLOC_TUNING=0`` turns it
off; other C libraries are left alone.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os

M_TRIM_THRESHOLD = -1
M_MMAP_THRESHOLD = -3
MMAP_THRESHOLD_BYTES = 64 << 20
TRIM_THRESHOLD_BYTES = 128 << 20


def tune_malloc() -> bool:
    """True when glibc accepted the fixed thresholds."""
    if os.environ.get("GEOLOC_MALLOC_TUNING", "1") == "0":
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


def release_free_memory() -> bool:
    """Hand the allocator's free memory back to the kernel (glibc ``malloc_trim(0)``, all arenas).

    Why: with the thresholds above, a 49 MP decode's buffers come from the per-thread arenas, and glibc
    keeps what they free (up to the 128 MB trim threshold each) after the request: eight concurrent 49 MP
    uploads left RSS 1.9 GB above idle for good (issue 18). Called after large decodes only; it costs a
    walk over the arenas (milliseconds). False where the C library has no malloc_trim."""
    global _libc_trim
    if _libc_trim is None:
        name = ctypes.util.find_library("c")
        try:
            _libc_trim = ctypes.CDLL(name).malloc_trim if name else False
        except (OSError, AttributeError):
            _libc_trim = False
    if not _libc_trim or os.environ.get("GEOLOC_MALLOC_TRIM", "1") == "0":
        return False
    _libc_trim(0)
    return True


#: BLAS threads while serving (``serving_blas_threads``); ``GEOLOC_BLAS_THREADS`` overrides.
SERVING_BLAS_THREADS = 1


def serving_blas_threads() -> int | None:
    """Limit the BLAS library (OpenBLAS under numpy) to one thread for a process that answers queries; the
    number of threads set, or None where threadpoolctl found no BLAS to limit.

    Why: a query's BLAS work is one vector through the PCA-whitening (a few ms), yet after each parallel
    call OpenBLAS's worker threads spin, busy, for about 2^28 cycles before they sleep, and that spinning
    falls on the next query's SIFT and CNN. Measured on 2 cores (``lite2-hybrid-384``, 1600 px photos, the
    service in-process): 234 ms of CPU and 118 ms of wall time per /locate with the default threads, 110 ms
    and 70 ms with one. A fit has its own fixed count (``fit_threads``)."""
    import numpy  # noqa: F401  (threadpoolctl limits the BLAS libraries already loaded: numpy's)
    from threadpoolctl import threadpool_info, threadpool_limits

    raw = os.environ.get("GEOLOC_BLAS_THREADS", "")
    n = int(raw) if raw.isdigit() and int(raw) > 0 else SERVING_BLAS_THREADS
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

    Why one thread, on every machine (issue 34): a parallel reduction sums in an order set by the thread
    count, so the same manifest fitted with 1 and with 2 BLAS threads gave another PCA (another float in the
    last place is enough to move a k-means assignment, a threshold, a ranked id), and the README's demo
    figures differed from one machine to the next. It is also faster where cores are busy: OpenMP's threads
    spin at every one of mini-batch k-means's small parallel steps, and on 2 loaded cores a fit's k-means
    took minutes with 2 threads (18.8 s against 6.8 s with one on 40,000 descriptors, the same centres).
    Feature extraction (onnxruntime, OpenCV) keeps its own threads: it is per image, and gives the same
    features with any count (tests/test_fit_reproducible.py)."""
    from threadpoolctl import threadpool_limits

    return threadpool_limits(limits=FIT_THREADS)

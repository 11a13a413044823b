"""What the inverted-file kinds for large collections share (``ivf-rabitq``, ``binary-ivf``).

Why their own base beside ``FaissIndex``: an IVF with a hashtable direct map (id -> list and offset) removes
an id in place at O(1) (FAISS swaps the last entry of the list into the hole), so these kinds keep no
tombstones (``removed_ids`` is always empty and ``compact`` has nothing to do) and need no ``IDMap2``: the
lists hold the ids themselves. The quantizer is learnt by ``train``, the explicit step at fit and refit, on
the fitting photos' codes or a sample of them, never on whichever batch is added first.
"""

from __future__ import annotations

import math

import faiss
import numpy as np
from faiss.contrib.clustering import two_level_clustering

from app.engine.index.base import IndexNotTrained
from app.engine.index.faiss_index import FaissIndex

#: FAISS warns below 39 training points per list; more than 64 adds time, not quality.
MIN_POINTS_PER_LIST, MAX_POINTS_PER_LIST = 39, 64


def default_nlist(n: int) -> int:
    """About 4 sqrt(n) lists, a power of two (FAISS's guidance: 4-16 sqrt(n)); 1,024 at 10^5, 4,096 at
    10^6, 16,384 at 10^7. More lists scan fewer codes per probe but cost more to train."""
    return max(1, 2 ** round(math.log2(max(4 * math.sqrt(max(n, 1)), 1))))


def usable_nlist(wanted: int | None, n_train: int) -> int:
    """``wanted`` (or ``default_nlist``) lists, no more than the training points support."""
    return max(1, min(wanted or default_nlist(n_train), n_train // MIN_POINTS_PER_LIST))


#: From this many lists on, the coarse centroids come from FAISS's two-level k-means. One k-means over
#: ``nlist`` centroids costs n_train x nlist distances per iteration, and both grow with the collection: 64
#: points per list at 16,384 lists is 1M x 16,384 x 25 iterations, hours on one core (the switch's training
#: at 4,096 lists already took minutes of one thread). Two levels (sqrt(nlist) clusters, then each split into its share
#: of the lists) cost about 2 sqrt(nlist) distances per point; ``bench.index_scale --kmeans`` measures both.
TWO_LEVEL_FROM = 1024
#: Full k-means iterations after the two levels (FAISS's one-level training runs 25).
REFINE_ITERATIONS = 3


def training_sample(x: np.ndarray, nlist: int) -> np.ndarray:
    """At most ``MAX_POINTS_PER_LIST`` points per list, drawn reproducibly."""
    m = nlist * MAX_POINTS_PER_LIST
    return x if len(x) <= m else x[np.random.default_rng(0).choice(len(x), m, replace=False)]


def two_level_centroids(x: np.ndarray, nlist: int, spherical: bool) -> np.ndarray:
    """``nlist`` centroids of float points ``x``: two-level k-means, then ``REFINE_ITERATIONS`` of k-means
    over all of them started from its centroids (a point near a first-level border was split among the wrong
    lists; the refinement moves it). Unit centroids when ``spherical``, for inner-product lists, as FAISS's own
    IVF training makes them."""
    x = np.ascontiguousarray(x, dtype=np.float32)
    start, _ = two_level_clustering(x, max(2, round(math.sqrt(nlist))), nlist, spherical=spherical, seed=1234)
    clustering = faiss.Clustering(x.shape[1], nlist)
    clustering.niter, clustering.spherical = REFINE_ITERATIONS, spherical
    clustering.max_points_per_centroid = 1 << 30  # x is already the training sample: no second subsampling
    faiss.copy_array_to_vector(np.ascontiguousarray(start, dtype=np.float32).ravel(), clustering.centroids)
    clustering.train(x, faiss.IndexFlatIP(x.shape[1]) if spherical else faiss.IndexFlatL2(x.shape[1]))
    return faiss.vector_to_array(clustering.centroids).reshape(nlist, x.shape[1])


class IvfListsIndex(FaissIndex):
    """A FAISS IVF (float or binary) with a hashtable direct map, searched ``nprobe`` lists deep."""

    def __init__(self, dim: int, binary: bool, nlist: int | None = None, nprobe: int = 64):
        self.nlist, self.nprobe = nlist, nprobe
        #: lists from which training uses two-level k-means (the bench sets it past nlist to measure one level)
        self.two_level_from = TWO_LEVEL_FROM
        super().__init__(dim, binary)

    def _make(self) -> None:
        return None  # the lists come from training

    def _adopt(self, index) -> None:
        """Take ``index`` (trained, loaded or copied) as this one's, with the direct map live changes need."""
        if index.direct_map.type != faiss.DirectMap.Hashtable:
            index.set_direct_map_type(faiss.DirectMap.Hashtable)
        index.nprobe = self.nprobe
        self._index, self.nlist, self.tombstones = index, index.nlist, set()

    def _require_trained(self):
        if not self.is_trained:
            raise IndexNotTrained(
                f"the {self.kind} index needs training before references are added: fit or refit the pipeline "
                "(`geoloc fit` / `geoloc refit`), which trains it on the fitting photos' codes"
            )
        return self._index

    # -- changes --------------------------------------------------------------------------------------
    def add(self, ids: np.ndarray, x: np.ndarray) -> None:
        """Add or replace (an id already stored is removed first: an add is an upsert, as a re-encode is)."""
        index = self._require_trained()
        ids = np.ascontiguousarray(ids, dtype=np.int64)
        x = self._prepare(x)
        if len(ids) != len(x):
            raise ValueError(f"{len(ids)} ids for {len(x)} codes")
        if len(np.unique(ids)) != len(ids):
            raise ValueError("duplicate ids in one add")
        self.remove(ids)
        index.add_with_ids(x, ids)

    def remove(self, ids) -> int:
        """Removed at once, in place: one hashtable lookup and one swap per id. Returns how many were stored."""
        if self._index is None:
            return 0
        ids = np.ascontiguousarray(np.atleast_1d(np.asarray(ids, dtype=np.int64)))
        return int(self._index.remove_ids(faiss.IDSelectorArray(ids))) if len(ids) else 0

    def _has(self, ref_id: int) -> bool:
        try:
            self._index.direct_map.get(ref_id)
            return True
        except RuntimeError:
            return False

    # -- reading --------------------------------------------------------------------------------------
    def ids(self) -> np.ndarray:
        """The ids in the lists, sorted (a scan of ``nlist`` lists, for rebuilds and checks, not searches)."""
        if self._index is None:
            return np.zeros(0, np.int64)
        inv = self._index.invlists
        parts = [
            faiss.rev_swig_ptr(inv.get_ids(lst), inv.list_size(lst)).copy()
            for lst in range(inv.nlist)
            if inv.list_size(lst)
        ]
        return np.sort(np.concatenate(parts)) if parts else np.zeros(0, np.int64)

    def params(self) -> dict:
        return {"nlist": self.nlist, "nprobe": self.nprobe}

    # -- files and copies -----------------------------------------------------------------------------
    def copy(self) -> IvfListsIndex:
        twin = object.__new__(type(self))
        twin.__dict__.update(self.__dict__)
        twin.tombstones = set()
        if self._index is not None:  # FAISS's serialised form: the one copy that works for every IVF kind
            read = faiss.deserialize_index_binary if self.binary else faiss.deserialize_index
            twin._adopt(read(self._serialize()))
        return twin

    def load(self, path) -> None:
        """Read what ``dump`` wrote; this object's ``nprobe`` (the configuration's) applies."""
        index = (faiss.read_index_binary if self.binary else faiss.read_index)(str(path))
        if index.d != self.dim:
            raise ValueError(f"{path} holds a {index.d}-d index; this one is {self.dim}-d")
        self._adopt(index)

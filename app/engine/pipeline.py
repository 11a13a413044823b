"""Compose the stages for one named configuration: image -> features -> aggregation -> codes.

The pipeline is split where the evaluation needs it: ``extract`` needs only the built CNN, while
``aggregate`` and ``encode`` need the fitted codebook, PCA and binariser. So an evaluation extracts every
image once and refits per fold, and a service encodes a query in one call (``encode_image``).
"""

from __future__ import annotations

import json
import os
import threading
import time
from collections.abc import Iterable, Sequence
from concurrent.futures import Future, ThreadPoolExecutor, wait
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from app.engine.added_models import register_added_models
from app.engine.artifacts import atomic_write_bytes, library_versions
from app.engine.calibration import Calibration
from app.engine.codes import Binariser
from app.engine.configs import PipelineConfig, configs_serving, get_config
from app.engine.dense import join_sampled, pool
from app.engine.errors import IncompatibleArtifact, ModelNotReady
from app.engine.imageio import ImageLimits, LoadedImage, load_image
from app.engine.index.references import ReferenceIndex
from app.engine.learned_whitening import LearnedWhitening, Place
from app.engine.matchers.base import Matcher
from app.engine.models.base import GlobalModel
from app.engine.pca import PcaWhitening, l2_normalize
from app.engine.registry import Kind, create, plugin
from app.engine.stored_profiles import StoredExtractor, get_profile
from app.engine.svm_bank import SvmBank
from app.engine.vlad import Codebook, vlad

PIPELINE_MANIFEST = "pipeline.json"
#: A decode keeps at least this many times the sides a pipeline's branches read. At 1 (decoding
#: at the branches' scale, JPEG DCT scaling to between 1x and 2x), a 1600 px JPEG was read at 800 px, the same
#: pixels as a PNG at 533 px (box reduce by 3) and its 12 MP original at 504 (DCT 1/8): three pictures for
#: one photo, and hybrid R@1 on whole photos fell (docs/results.md). At 2 a 1600 px photo is decoded whole
#: whatever its container, a 12 MP one at 1/4 (JPEG) or by a box of 4 (PNG), and the branches' area filters
#: do the rest.
DECODE_OVERSAMPLE = 2
PIPELINE_FORMAT = 1


@dataclass
class Features:
    """What one image yields before aggregation."""

    local: np.ndarray | None  # (N, D) descriptors to aggregate (RootSIFT/ORB bits, or hybrid)
    xy: np.ndarray | None  # (N, 2) keypoint positions as fractions of width/height
    global_: np.ndarray | None  # (C,) GeM of the global model's dense map, L2-normalised
    timings_ms: dict[str, float] = field(default_factory=dict)
    orb_raw: np.ndarray | None = None  # packed ORB bits, for Hamming matching
    config: str | None = None  # the configuration that extracted them (a re-fit may change it)

    @property
    def n_local(self) -> int:
        return 0 if self.local is None else len(self.local)


@dataclass
class Codes:
    float_: np.ndarray | None  # (dim,) float32, L2-normalised
    binary: np.ndarray | None  # (bits/8,) uint8
    features_extracted: int = 0
    features_kept: int = 0
    timings_ms: dict[str, float] = field(default_factory=dict)


class _Timer:
    def __init__(self, sink: dict[str, float], name: str):
        self.sink, self.name = sink, name

    def __enter__(self):
        self.t = time.perf_counter()

    def __exit__(self, *exc):
        self.sink[self.name] = self.sink.get(self.name, 0.0) + (time.perf_counter() - self.t) * 1000


#: Runs the global model of a hybrid while the caller's thread extracts local features: OpenCV's SIFT and
#: onnxruntime release the GIL and neither keeps two cores busy alone, so the two branches overlap (a photo's
#: extraction takes less time on two cores). Shared by every pipeline in the process, bounded, so concurrent
#: requests queue here instead of adding threads. Made per process: a forked child would inherit an executor
#: whose threads it does not have.
_BRANCHES: tuple[int, ThreadPoolExecutor] | None = None
_BRANCHES_LOCK = threading.Lock()


def _branches() -> ThreadPoolExecutor:
    global _BRANCHES
    with _BRANCHES_LOCK:
        if _BRANCHES is None or _BRANCHES[0] != os.getpid():
            _BRANCHES = (os.getpid(), ThreadPoolExecutor(max_workers=4, thread_name_prefix="geoloc-cnn"))
        return _BRANCHES[1]


def _settle(job: Future | None) -> None:
    """Cancel a branch's job that has not started, or wait for one that has (its outcome is not wanted).
    Why wait: a thread cannot be stopped, and a job left running after its request failed held memory that
    no extraction slot accounted for."""
    if job is not None and not job.cancel():
        wait([job])


def _unit(x: np.ndarray) -> np.ndarray:
    return l2_normalize(np.asarray(x, np.float32))


class Pipeline:
    def __init__(
        self,
        config: PipelineConfig,
        global_model: GlobalModel | None = None,
        codebook: Codebook | None = None,
        pca: PcaWhitening | LearnedWhitening | None = None,
        binariser: Binariser | None = None,
        manifest: dict | None = None,
        bank: SvmBank | None = None,
        models_dir: Path | None = None,
        calibration: Calibration | None = None,
    ):
        """``models_dir`` holds the built models (the global model, learned local extractors); a
        ``global_model`` given here (loaded once, shared by tests or an evaluation) wins over the one the
        registry would build from the models dir."""
        self.config = config
        register_added_models(models_dir)  # a model the user added to it is a plug-in like a built-in
        if config.uses_global_model and global_model is None:
            if models_dir is None:
                raise ModelNotReady(
                    f"configuration {config.name} needs the {config.global_model} model: give the models dir"
                )
            global_model = create(Kind.GLOBAL_MODEL, config.global_model, models_dir)
        self.global_model = global_model if config.uses_global_model else None
        self.models_dir = models_dir
        self._matcher: Matcher | None = None
        self._stored_extractor: StoredExtractor | None = None
        self.codebook = codebook
        self.pca = pca
        self.binariser = binariser
        self.manifest = manifest or {}
        self.bank = bank  # SVM bank: which local features to aggregate (None = all)
        #: The confidence rule and ``p_within_25m``, fitted on the collection
        #: (``app.usecases.fitting.calibrate_collection``);
        #: the conservative rule until then.
        self.calibration: Calibration = calibration or Calibration.conservative("this pipeline is not calibrated")
        self.bank_select = "positive"  # or "negative" (the thesis ablation)
        #: The index kinds' trained state (IVF's quantizer), empty; None when the kinds need no training.
        self.trained_index: ReferenceIndex | None = None
        self.source: PipelineSource | None = None  # set when loaded from disk (see PipelineSource)
        self._local = (
            create(
                Kind.LOCAL_EXTRACTOR,
                config.local,
                models_dir,
                max_keypoints=config.max_keypoints,
                long_side=config.local_long_side,
            )
            if config.local
            else None
        )

    def load_models(self) -> None:
        """Load every ONNX model now (a service wants a missing file at start-up, not at its first query)."""
        if self.global_model is not None:
            self.global_model.load()
        model = getattr(self._local, "model", None)  # learned extractors hold an OnnxModel
        if model is not None:
            model.load()
        if self.stored_extractor is not None:
            self.stored_extractor.load()

    @property
    def matcher(self) -> Matcher:
        """The configuration's matcher (verification, /locate's ``rerank``), built on first use: most requests
        never verify."""
        if self._matcher is None:
            self._matcher = create(Kind.MATCHER, self.config.matcher, self.models_dir)
        return self._matcher

    @property
    def stored_extractor(self) -> StoredExtractor | None:
        """The configuration's stored local-features extractor (``app.engine.stored_profiles``), or None when
        it stores none: the record of each reference at encoding, the query's features at /locate."""
        name = self.config.stored_features
        if name is None:
            return None
        if self._stored_extractor is None:
            if self.models_dir is None:
                raise ModelNotReady(f"configuration {self.config.name} stores XFeat features: give the models dir")
            self._stored_extractor = StoredExtractor(get_profile(name), self.models_dir)
        return self._stored_extractor

    # -- stage 0: decode ------------------------------------------------------------------------------
    @property
    def decode_sides(self) -> tuple[int, int]:
        """(long side, short side) the branches read from a decoded image: the local extractor's long side
        and the global model's short side. ``decode`` keeps ``DECODE_OVERSAMPLE`` times each."""
        c = self.config
        long_side = c.local_long_side if c.local else 0
        short_side = max(c.cnn_short_side, c.cnn_second_short_side or 0) if c.uses_global_model else 0
        return long_side, short_side

    def decode(self, data: bytes, limits: ImageLimits | None = None) -> LoadedImage:
        """Decode an image for this pipeline (``load_image`` with ``limits``, keeping at least
        ``DECODE_OVERSAMPLE`` times the sides ``decode_sides`` reads): the one decode of queries, references,
        fitting and evaluation, so all see the same pixels. Each branch then resizes with its own area
        filter from at least twice its size, so the container's reduction (JPEG's DCT scaling, PNG's box
        reduce, or none) no longer decides which pixels a branch sees."""
        long_side, short_side = self.decode_sides
        return load_image(
            data,
            limits,
            decode_long_side=max(long_side * DECODE_OVERSAMPLE, 1),
            decode_short_side=short_side * DECODE_OVERSAMPLE,
        )

    # -- stage 1: features ----------------------------------------------------------------------------
    def extract(self, rgb: np.ndarray) -> Features:
        c = self.config
        t: dict[str, float] = {}
        local = xy = gem = orb_raw = None
        cnn = None
        if self.global_model is not None and self._local is not None:  # both branches at once
            cnn = _branches().submit(self._dense, rgb)
        if self._local is not None:
            try:
                with _Timer(t, "local_features"):
                    lf = self._local(rgb)
            except BaseException:
                _settle(cnn)  # no work of this request may outlive its answer
                raise
            local, xy, orb_raw = lf.descriptors, lf.xy, lf.raw
        if self.global_model is not None:
            dense, second_gem, t["cnn"] = cnn.result() if cnn is not None else self._dense(rgb)
            if c.cnn_global_weight > 0 or local is None:
                gem = pool(dense, c.global_pooling, c.gem_p)
                if second_gem is not None:
                    gem = _unit(gem + second_gem)
            if c.cnn_local_weight > 0 and local is not None:
                with _Timer(t, "hybrid"):
                    local = join_sampled(local, dense, xy, c.cnn_local_weight)
        return Features(local=local, xy=xy, global_=gem, timings_ms=t, orb_raw=orb_raw, config=c.name)

    def _dense(self, rgb: np.ndarray) -> tuple[np.ndarray, np.ndarray | None, float]:
        """The global model's map, the GeM of its map at the second size (``cnn_second_short_side``; None
        without one or where no GeM is pooled), and their own time in ms (it may overlap the local
        features')."""
        c = self.config
        t0 = time.perf_counter()
        dense = self.global_model.dense(rgb, c.cnn_short_side)
        second = None
        if c.cnn_second_short_side is not None and (c.cnn_global_weight > 0 or c.local is None):
            second = pool(self.global_model.dense(rgb, c.cnn_second_short_side), c.global_pooling, c.gem_p)
        return dense, second, (time.perf_counter() - t0) * 1000

    # -- stage 1b: feature selection (SVM bank) -------------------------------------------------------
    def select(self, f: Features) -> np.ndarray | None:
        """Keep-mask from the SVM bank, or None when there is no bank (keep all)."""
        if self.bank is None or f.local is None or f.n_local == 0:
            return None
        t0 = time.perf_counter()
        keep = self.bank.keep(f.local, self.bank_select)
        f.timings_ms["svm"] = (time.perf_counter() - t0) * 1000  # set, not added: features may be reused
        return keep

    # -- stage 2: aggregation -------------------------------------------------------------------------
    def aggregate(self, f: Features, keep: np.ndarray | None = None) -> np.ndarray:
        """One L2-normalised vector per image; ``keep`` (bool mask) selects local features (SVM bank)."""
        c = self.config
        parts = []
        if c.local is not None:
            if self.codebook is None:
                raise ModelNotReady(f"configuration {c.name} is not fitted (no codebook)")
            local = f.local if keep is None else f.local[keep]
            parts.append(vlad(local, self.codebook, c.power_law, c.intra_norm))
        if f.global_ is not None:
            w = c.cnn_global_weight if c.local is not None else 1.0
            parts.append(w * f.global_)
        return _unit(np.concatenate(parts)).astype(np.float32)

    # -- stage 3: codes -------------------------------------------------------------------------------
    def encode_vector(self, v: np.ndarray) -> tuple[np.ndarray | None, np.ndarray | None]:
        reduced = self.pca.transform(v) if self.pca is not None else _unit(v)
        f = reduced.astype(np.float32) if self.config.float_codes else None
        b = self.binariser.encode(reduced) if self.binariser is not None else None
        return f, b

    def encode_features(self, f: Features, keep: np.ndarray | None = None) -> Codes:
        t = dict(f.timings_ms)
        with _Timer(t, "aggregate"):
            v = self.aggregate(f, keep)
        with _Timer(t, "codes"):
            fc, bc = self.encode_vector(v)
        kept = f.n_local if keep is None else int(np.sum(keep))
        return Codes(fc, bc, f.n_local, kept, t)

    def encode_image(self, rgb: np.ndarray, use_bank: bool = False) -> Codes:
        """References are encoded from all their features; queries may go through the bank first."""
        f = self.extract(rgb)
        return self.encode_features(f, self.select(f) if use_bank else None)

    @property
    def float_dim(self) -> int | None:
        if not self.config.float_codes:
            return None
        if self.pca is not None:
            return self.pca.dim
        d = self.codebook.k * self.codebook.dim if self.codebook is not None else 0
        uses_gem = self.config.cnn_global_weight > 0 or self.config.local is None
        return d + (plugin(Kind.GLOBAL_MODEL, self.config.global_model).dim if uses_gem else 0)

    @property
    def bits(self) -> int | None:
        return self.binariser.bits if self.binariser is not None else None

    # -- fitting --------------------------------------------------------------------------------------
    def fit(
        self,
        features: list[Features],
        seed: int = 0,
        progress: Iterable | None = None,
        codebook: Codebook | None = None,
        places: Sequence[Place | None] | None = None,
    ) -> None:
        """Fit codebook, then PCA-whitening, then the binariser, each on the previous stage's output.
        ``codebook``: take this one instead of fitting one (the calibration's auxiliary fits, which leave
        references out of the whitening, reuse the served pipeline's codebook: k-means is most of a fit's time).
        ``places``: where each of ``features`` was taken (None where unknown); a configuration with learned
        whitening needs them (its matching pairs are the photos within ``lw_pos_radius_m`` of each other)."""
        c = self.config
        if not features:
            raise ModelNotReady(f"nothing to fit {c.name} on: no db or train images were given")
        rng = np.random.default_rng(seed)
        if codebook is not None:
            self.codebook = codebook
        elif c.local is not None:
            sample = []
            for f in features:
                if f.n_local:
                    n = min(c.codebook_samples_per_image, f.n_local)
                    sample.append(f.local[rng.choice(f.n_local, n, replace=False)])
            if not sample:
                raise ModelNotReady("no local features in the training images: cannot fit a codebook")
            self.codebook = Codebook.fit(np.vstack(sample), c.k, c.codebook, seed=seed)
        vectors = np.stack([self.aggregate(f) for f in features])
        self.pca = self._fit_whitening(vectors, places, seed) if c.pca_dim else None
        reduced = self.pca.transform(vectors) if self.pca is not None else vectors
        self.binariser = Binariser.fit(reduced, c.bits, c.binary, seed) if c.binary else None
        self.trained_index = self.train_index(vectors)
        self.manifest = {"n_train_images": len(features), "seed": seed}

    def train_index(self, vectors: np.ndarray) -> ReferenceIndex | None:
        """The explicit training step of the index kinds that need one (IVF's quantizer), on the codes of
        the fitting photos' ``vectors`` (aggregated, before whitening); None for kinds that need none.

        Why the trained state lives with the fitted pipeline (saved beside the codebook and PCA, retrained
        whenever they are): it describes the pipeline's code space, and codes change only when the pipeline
        is fitted again (`geoloc fit`, refit's new generation, each evaluation fold). So every index of those
        codes (a rebuild from the database, another replica, the SVM bank's training) starts from the same
        quantizer, a snapshot's files carry it, and nothing is learnt from whichever batch is added first."""
        index = ReferenceIndex(self.config, self.float_dim, self.bits, serving=configs_serving)
        if index.is_trained:
            return None
        index.train(*self.encode_vector(vectors))
        return index

    def new_index(
        self, kinds: dict[str, str] | None = None, params: dict[str, dict[str, Any]] | None = None
    ) -> ReferenceIndex:
        """An empty index of this pipeline's codes, of the configuration's kinds, trained: the one way the
        service makes one (live collection, snapshots, the SVM bank's training, the evaluation). With
        ``kinds`` (a part's kind where it is not the configuration's: a snapshot of an index that switched by
        size, a shared index server) and ``params`` (a part's ``build_index`` arguments), an untrained one of
        those kinds, which its caller loads or fills."""
        if kinds is None and params is None:
            if self.trained_index is not None:
                return self.trained_index.copy()
            return ReferenceIndex(self.config, self.float_dim, self.bits, serving=configs_serving)
        return ReferenceIndex(
            self.config, self.float_dim, self.bits, kinds=kinds, params=params, serving=configs_serving
        )

    def _fit_whitening(
        self, vectors: np.ndarray, places: Sequence[Place | None] | None, seed: int
    ) -> PcaWhitening | LearnedWhitening:
        c = self.config
        if c.whitening == "pca":
            return PcaWhitening.fit(vectors, c.pca_dim, c.whiten_power, seed)
        if places is None:
            raise ModelNotReady(f"configuration {c.name} learns its whitening from GPS pairs: give the places")
        return LearnedWhitening.fit(
            vectors,
            places,
            c.pca_dim,
            pos_radius_m=c.lw_pos_radius_m,
            neg_radius_m=c.lw_neg_radius_m,
            pre_dim=c.lw_pre_dim,
            shrinkage=c.lw_shrinkage,
        )

    # -- persistence ----------------------------------------------------------------------------------
    def save(self, directory: Path, extra: dict | None = None) -> None:
        directory.mkdir(parents=True, exist_ok=True)
        if self.codebook is not None:
            self.codebook.save(directory)
        if self.pca is not None:
            self.pca.save(directory)
        if self.binariser is not None:
            self.binariser.save(directory)
        if self.bank is not None:
            self.bank.save(directory)
        self.calibration.save(directory)
        if self.trained_index is not None:
            self.trained_index.save_trained(directory)
        manifest = {
            "format_version": PIPELINE_FORMAT,
            "config": self.config.model_dump(),
            "fitted_at": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
            "libraries": library_versions(),
            "float_dim": self.float_dim,
            "bits": self.bits,
            **self.manifest,
            **(extra or {}),
        }
        atomic_write_bytes(directory / PIPELINE_MANIFEST, json.dumps(manifest, indent=1).encode())

    @classmethod
    def load(cls, directory: Path, global_model: GlobalModel | None = None, models_dir: Path | None = None) -> Pipeline:
        mpath = directory / PIPELINE_MANIFEST
        if not mpath.exists():
            raise ModelNotReady(f"no fitted pipeline in {directory}: run `geoloc fit` first")
        manifest = json.loads(mpath.read_text())
        if manifest.get("format_version") != PIPELINE_FORMAT:
            raise IncompatibleArtifact(
                f"{mpath} has format {manifest.get('format_version')}, expected {PIPELINE_FORMAT}"
            )
        saved = PipelineConfig(**manifest["config"])
        register_added_models(models_dir)
        known = get_config(saved.name)
        if saved != known:
            raise IncompatibleArtifact(
                f"{directory} was fitted with an older definition of {saved.name!r}; refit it (`geoloc fit`)"
            )
        c = known
        pipe = cls(
            c,
            global_model=global_model,
            codebook=Codebook.load(directory) if c.local else None,
            pca=_load_whitening(c, directory),
            binariser=Binariser.load(directory) if c.binary else None,
            manifest=manifest,
            bank=SvmBank.load(directory) if SvmBank.exists(directory) else None,
            models_dir=models_dir,
            calibration=Calibration.load(directory),
        )
        trained = ReferenceIndex(c, pipe.float_dim, pipe.bits, serving=configs_serving)
        if not trained.is_trained:
            trained.load_trained(directory)
            pipe.trained_index = trained if trained.is_trained else None
        return pipe

    @property
    def fingerprint(self) -> str:
        """Identifies the fitted state; an index built with another fingerprint must be re-encoded."""
        parts = [self.config.name]
        for a in (self.codebook, self.pca, self.binariser):
            if a is not None:
                parts.append(str(a.manifest.get("data_hash")))
        return ":".join(parts)


def _load_whitening(c: PipelineConfig, directory: Path) -> PcaWhitening | LearnedWhitening | None:
    if not c.pca_dim:
        return None
    return LearnedWhitening.load(directory) if c.whitening == "learned" else PcaWhitening.load(directory)


def pipeline_dir(models_dir: Path, config_name: str) -> Path:
    return models_dir / "pipelines" / config_name


@dataclass(frozen=True)
class PipelineSource:
    """Where a fitted pipeline is loaded from: the ONNX models dir and the fitted pipeline's folder.

    Why a value of its own: whatever encodes away from the process that chose the pipeline (an encoder
    thread pool, a Ray actor on another machine, a re-index into a new generation) is handed this small,
    picklable value and loads exactly the same pipeline from it."""

    models_dir: Path
    directory: Path
    config: str

    @classmethod
    def default(cls, models_dir: Path, config_name: str) -> PipelineSource:
        return cls(Path(models_dir), pipeline_dir(Path(models_dir), config_name), config_name)

    def load(self) -> Pipeline:
        pipe = Pipeline.load(self.directory, models_dir=self.models_dir)
        pipe.load_models()
        pipe.source = self
        return pipe


def load_pipeline(models_dir: Path, config_name: str) -> Pipeline:
    return PipelineSource.default(models_dir, config_name).load()

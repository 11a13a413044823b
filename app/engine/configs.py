"""Named pipeline configurations: one name means exactly one pipeline (the hloc ``confs`` shape).

A fitted model records its configuration in its manifest, so ``--config hybrid-bin`` today and a reload
next month build the same thing. Sizes and counts were chosen by measurement on penn-campus-gps with
``geoloc eval --folds`` (docs/results.md has the figures).
"""

from __future__ import annotations

import json
from typing import ClassVar, Literal

from pydantic import BaseModel, ConfigDict, field_validator, model_validator

from app.engine.errors import GeolocError


class UnknownConfig(GeolocError):
    pass


class PipelineConfig(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid")

    name: str
    description: str
    #: The local-feature extractor (a registry name, ``app.engine.registry``), or None for a global-only
    #: pipeline.
    local: str | None = "sift"
    local_long_side: int = 640
    max_keypoints: int = 1000
    #: The global model (a registry name, ``app.engine.registry``): its dense map is sampled at the
    #: keypoints (hybrid, ``cnn_local_weight``) and/or GeM-pooled into a global descriptor
    #: (``cnn_global_weight``). The ``cnn_*`` fields are that model's settings (the names predate the
    #: registry and stay, so pipelines fitted before it load unchanged).
    global_model: str = "squeezenet"
    cnn_short_side: int = 448
    #: A second input size (short side) whose map's GeM is averaged with the first's (multi-scale pooling,
    #: Radenovic et al.: the two L2-normalised GeM vectors summed, then normalised); the keypoints sample the
    #: first size's map only. None: one size.
    cnn_second_short_side: int | None = None
    cnn_local_weight: float = 0.0  # > 0: feature-level hybrid, fire9 sampled at each keypoint
    cnn_global_weight: float = 0.0  # > 0: GeM vector joined to the aggregated one (image-level hybrid)
    gem_p: float = 3.0
    #: How the global model's map becomes the global descriptor: ``gem`` (GeM with ``gem_p``), or ``none`` for
    #: a model whose output already is one (a (1, 1, D) map: a model added with a ``global`` output,
    #: ``app.engine.added_models``), used as it is; such a map cannot be sampled at keypoints.
    global_pooling: Literal["gem", "none"] = "gem"
    #: Aggregation of local features.
    codebook: Literal["kmeans", "minibatch"] | None = "minibatch"
    k: int = 64
    power_law: float = 0.5
    intra_norm: bool = True
    codebook_samples_per_image: int = 300
    #: Codes: PCA-whitened floats (pca_dim None = full dimension, no PCA) and/or binary codes.
    pca_dim: int | None = 256
    whiten_power: float = 0.5
    #: ``pca``: PCA-whitening (``whiten_power``); ``learned``: whitening learned from the fitting photos' GPS
    #: pairs (app/engine/learned_whitening.py: matching pairs within ``lw_pos_radius_m``, non-matching beyond
    #: ``lw_neg_radius_m``), after an unwhitened PCA to ``lw_pre_dim``, the pair covariance shrunk by
    #: ``lw_shrinkage``. Both give ``pca_dim`` dimensions.
    whitening: Literal["pca", "learned"] = "pca"
    lw_pos_radius_m: float = 25.0
    lw_neg_radius_m: float = 100.0
    lw_pre_dim: int = 512
    lw_shrinkage: float = 0.1
    float_codes: bool = True
    binary: Literal["sign", "itq"] | None = None
    bits: int = 256
    #: Index kinds, by registry name (``app.engine.index.base``: flat is exact; ivf / hnsw for large collections).
    float_index: str = "flat"
    binary_index: str = "flat"
    shortlist: int = 100  # two-stage: binary shortlist size before the float re-rank
    #: Where both kinds are ``flat``, a large collection switches to the compressed kinds (ivf-rabitq for
    #: floats, binary-ivf for bits) once it holds ``Settings.index_switch_at`` references
    #: (``Collection``). False: the named kinds serve at every size. A configuration that names another kind
    #: keeps it whatever this says.
    index_by_size: bool = True
    #: ``geoloc fit`` trains an SVM bank (from the collection, method.md "SVM bank") and queries aggregate
    #: only the features it keeps; False aggregates every feature. Ignored without local features. The
    #: default is True so that the definitions fitted before this field existed stay equal (Pipeline.load).
    svm_bank: bool = True
    #: The matcher that verifies the top candidates (verification, /locate's ``rerank``), by registry name.
    matcher: str = "sift-mnn"
    #: The stored local-features profile (``app.engine.stored_profiles``): each reference's record is made at
    #: encoding and stored beside it, and /locate verifies the top candidates from those records by default
    #: (the query's features extracted once). None: nothing stored; verification is ``rerank=true``'s, by
    #: ``matcher``, re-extracting each candidate.
    stored_features: str | None = None

    #: Fields that change what ``Pipeline.extract`` returns (the evaluation caches features by them).
    EXTRACTION_FIELDS: ClassVar[tuple[str, ...]] = (
        "local",
        "local_long_side",
        "max_keypoints",
        "global_model",
        "cnn_short_side",
        "cnn_second_short_side",
        "cnn_local_weight",
        "cnn_global_weight",
        "gem_p",
        "global_pooling",
    )

    @field_validator("stored_features")
    @classmethod
    def _known_profile(cls, name: str | None) -> str | None:
        if name is not None:
            from app.engine.stored_profiles import get_profile

            get_profile(name)
        return name

    @model_validator(mode="after")
    def _vector_is_not_sampled(self) -> PipelineConfig:
        if self.global_pooling == "none" and (self.cnn_local_weight > 0 or self.cnn_second_short_side is not None):
            raise ValueError(
                "a global model whose output is a vector (global_pooling none) has no map to sample at keypoints "
                "or to pool at a second size: cnn_local_weight 0 and no cnn_second_short_side"
            )
        return self

    def extraction_key(self) -> str:
        """The extraction fields' values; a field at its default that older keys lacked (``global_pooling``)
        is left out, so feature caches written before it stay valid."""
        fields = {f: getattr(self, f) for f in self.EXTRACTION_FIELDS}
        if fields["global_pooling"] == "gem":
            del fields["global_pooling"]
        return json.dumps(fields, sort_keys=True)

    def with_overrides(self, overrides: dict[str, str]) -> PipelineConfig:
        """A variant for experiments (``geoloc eval --set k=32``); it keeps the name with a suffix."""
        if not overrides:
            return self
        data = self.model_dump()
        unknown = set(overrides) - set(data)
        if unknown:
            raise UnknownConfig(f"unknown configuration fields {sorted(unknown)}")
        data.update(overrides)
        data["name"] = self.name + "[" + ",".join(f"{k}={v}" for k, v in sorted(overrides.items())) + "]"
        return PipelineConfig.model_validate(data)

    @property
    def uses_global_model(self) -> bool:
        return self.cnn_local_weight > 0 or self.cnn_global_weight > 0 or self.local is None

    @property
    def modes(self) -> list[str]:
        """Search modes this configuration can serve, the best first."""
        if self.float_codes and self.binary:
            return ["two-stage", "float", "binary"]
        if self.float_codes:
            return ["float"]
        return ["binary"]


_HYBRID = dict(local="sift", cnn_local_weight=1.0, cnn_global_weight=1.0, codebook="minibatch", k=64, pca_dim=256)
# XFeat (learned, 64-d) in place of RootSIFT; keypoints and image size chosen with --folds 5 on
# penn-campus-gps (docs/results.md, "XFeat local features").
_XFEAT = dict(local="xfeat", local_long_side=640, max_keypoints=1024)

CONFIGS: dict[str, PipelineConfig] = {
    c.name: c
    for c in [
        PipelineConfig(
            name="sift-vlad-kmeans",
            description="Baseline: RootSIFT, Lloyd k-means codebook, VLAD (signed sqrt + L2), full dimension, "
            "exhaustive float search",
            local="sift",
            codebook="kmeans",
            intra_norm=False,
            pca_dim=None,
        ),
        PipelineConfig(
            name="sift-mbvlad",
            description="RootSIFT MBVLAD (mini-batch codebook, power-law, intra-norm), PCA-whitened floats",
            local="sift",
            codebook="minibatch",
            whiten_power=0.25,
        ),
        PipelineConfig(
            name="orb-mbvlad-bin",
            description="ORB MBVLAD, PCA then ITQ binary codes, Hamming search",
            local="orb",
            codebook="minibatch",
            float_codes=False,
            binary="itq",
            bits=256,
        ),
        PipelineConfig(
            name="squeezenet-gem",
            description="SqueezeNet fire9 GeM-pooled global descriptor, PCA-whitened floats",
            local=None,
            codebook=None,
            cnn_global_weight=1.0,
            whiten_power=0.25,
        ),
        PipelineConfig(
            name="hybrid",
            description="Feature-level hybrid (RootSIFT + fire9 sampled at each keypoint) MBVLAD, joined with "
            "fire9 GeM, PCA-whitened floats (the former default)",
            **_HYBRID,
        ),
        PipelineConfig(
            name="hybrid-fast",
            description="The default hybrid with RootSIFT on fewer pixels (512 px long side instead of 640): the "
            "same recall on penn-campus-gps; no faster per /locate (SIFT runs beside the CNN, the longer branch)",
            **{**_HYBRID, "local_long_side": 512},
        ),
        PipelineConfig(
            name="hybrid-faster",
            description="hybrid-fast with SqueezeNet on fewer pixels too (336 px short side instead of 448)",
            **{**_HYBRID, "local_long_side": 512, "cnn_short_side": 336},
        ),
        PipelineConfig(
            name="hybrid-lg",
            description="The default hybrid, verified by XFeat keypoints matched with LighterGlue (a learned "
            "matcher) and the H-or-F geometry, in place of RootSIFT mutual nearest neighbours",
            matcher="xfeat-lighterglue",
            **_HYBRID,
        ),
        PipelineConfig(
            name="hybrid-nobank",
            description="The default hybrid without the SVM bank: every local feature of a query is aggregated",
            svm_bank=False,
            **_HYBRID,
        ),
        PipelineConfig(
            name="hybrid-bin",
            description="The hybrid descriptor with ITQ binary codes for a Hamming shortlist and float codes "
            "for the exact re-rank",
            binary="itq",
            bits=256,
            **_HYBRID,
        ),
        PipelineConfig(
            name="xfeat-mbvlad",
            description="XFeat descriptors (learned, 64-d) MBVLAD, PCA-whitened floats",
            codebook="minibatch",
            whiten_power=0.25,
            **_XFEAT,
        ),
        PipelineConfig(
            name="hybrid-xfeat",
            description="Feature-level hybrid with XFeat in place of RootSIFT (fire9 sampled at XFeat keypoints) "
            "MBVLAD, joined with fire9 GeM, PCA-whitened floats",
            **{**_HYBRID, **_XFEAT},
        ),
    ]
}

# EfficientNet-Lite2 (ImageNet, from the pinned wheel; app/engine/models/efficientnet_lite.py) as the global
# model: its head map (1280, stride 32) or its richest stride-16 map (720) GeM-pooled, alone or joined with
# the RootSIFT MBVLAD (image-level hybrid), and the stride-16 map sampled at every keypoint (the lite2-hybrid
# family: the feature-level hybrid of the default with Lite2 in place of fire9, the best recall measured).
# Figures: docs/results.md, "EfficientNet-Lite2" and "The Lite2 map at each keypoint".
_LITE2 = dict(global_model="efficientnet-lite2", cnn_short_side=448)
_LITE2_HYBRID = {**_HYBRID, **_LITE2, "global_model": "efficientnet-lite2-mid"}
for _config in [
    PipelineConfig(
        name="lite2-gem",
        description="EfficientNet-Lite2 head map (1280 channels) GeM-pooled global descriptor, PCA-whitened floats",
        local=None,
        codebook=None,
        cnn_global_weight=1.0,
        whiten_power=0.25,
        **_LITE2,
    ),
    PipelineConfig(
        name="lite2-mid-gem",
        description="EfficientNet-Lite2 stride-16 map (720 channels) GeM-pooled global descriptor, PCA-whitened floats",
        local=None,
        codebook=None,
        cnn_global_weight=1.0,
        whiten_power=0.25,
        **{**_LITE2, "global_model": "efficientnet-lite2-mid"},
    ),
    PipelineConfig(
        name="hybrid-lite2",
        description="RootSIFT MBVLAD joined with the EfficientNet-Lite2 head GeM (image-level hybrid), "
        "PCA-whitened floats",
        local="sift",
        codebook="minibatch",
        k=64,
        pca_dim=256,
        cnn_global_weight=1.0,
        **_LITE2,
    ),
    PipelineConfig(
        name="lite2-hybrid",
        description="Feature-level hybrid with EfficientNet-Lite2's stride-16 map (720 channels) in place of "
        "SqueezeNet's fire9: RootSIFT joined with the map sampled at each keypoint, MBVLAD, joined with the "
        "map's GeM, PCA-whitened floats",
        **_LITE2_HYBRID,
    ),
    PipelineConfig(
        name="lite2-hybrid-fast",
        description="lite2-hybrid on fewer pixels: RootSIFT at 512 px (long side), EfficientNet-Lite2 at 384 px "
        "(short side)",
        **{**_LITE2_HYBRID, "local_long_side": 512, "cnn_short_side": 384},
    ),
    PipelineConfig(
        name="lite2-hybrid-faster",
        description="lite2-hybrid-fast with EfficientNet-Lite2 at 336 px (short side)",
        **{**_LITE2_HYBRID, "local_long_side": 512, "cnn_short_side": 336},
    ),
    PipelineConfig(
        name="lite2-hybrid-384",
        description="lite2-hybrid on the fewest pixels that still win: RootSIFT at 384 px (long side), "
        "EfficientNet-Lite2 at 336 px (short side)",
        **{**_LITE2_HYBRID, "local_long_side": 384, "cnn_short_side": 336},
    ),
    PipelineConfig(
        name="lite2-hybrid-384-lw",
        description="lite2-hybrid-384 with whitening learned from the collection's GPS pairs (references within "
        "25 m as matching pairs; Radenovic, Tolias and Chum 2018) in place of PCA-whitening",
        whitening="learned",
        **{**_LITE2_HYBRID, "local_long_side": 384, "cnn_short_side": 336},
    ),
    PipelineConfig(
        name="lite2-hybrid-384-2s",
        description="lite2-hybrid-384 with the EfficientNet-Lite2 map GeM-pooled at two input sizes (336 and "
        "448 px short side, the two GeM vectors averaged); the keypoints sample the 336 px map",
        cnn_second_short_side=448,
        **{**_LITE2_HYBRID, "local_long_side": 384, "cnn_short_side": 336},
    ),
    PipelineConfig(
        name="lite2-hybrid-384-sv",
        description="lite2-hybrid-384 with stored verification: each reference's XFeat features (640 px, 900 "
        "keypoints, about 60 KB) stored at ingestion, and the top 10 candidates of every answer verified from "
        "them (the query's XFeat features extracted once)",
        stored_features="xfeat-640-n900",
        **{**_LITE2_HYBRID, "local_long_side": 384, "cnn_short_side": 336},
    ),
    PipelineConfig(
        name="hybrid-lite2-mid",
        description="RootSIFT MBVLAD joined with the EfficientNet-Lite2 stride-16 map GeM (image-level hybrid), "
        "PCA-whitened floats",
        local="sift",
        codebook="minibatch",
        k=64,
        pca_dim=256,
        cnn_global_weight=1.0,
        **{**_LITE2, "global_model": "efficientnet-lite2-mid"},
    ),
]:
    CONFIGS[_config.name] = _config

# The same pipelines over the index kinds for 10^6-10^7 references (IVF with an exact quantizer:
# RaBitQ codes re-ranked exactly from the float codes; binary IVF for Hamming codes). The codes, and so the
# fitted pipelines, are those of the configurations they derive from; only the index differs.
for _base, _kinds in [
    ("lite2-hybrid-384", dict(float_index="ivf-rabitq")),
    ("hybrid-bin", dict(float_index="ivf-rabitq", binary_index="binary-ivf")),
]:
    _config = CONFIGS[_base].model_copy(
        update={
            "name": f"{_base}-ivf",
            "description": f"{_base} searched through "
            + " and ".join(sorted(set(_kinds.values())))
            + " (the index kinds for 10^6-10^7 references)",
            **_kinds,
        }
    )
    CONFIGS[_config.name] = _config

# The default: it beats hybrid at R@1, R@5 and confident-and-right answers on penn-campus-gps (5 folds), in
# less /locate time than hybrid (docs/results.md, "A faster default"). Data dirs built before keep the
# configuration they record.
DEFAULT_CONFIG = "lite2-hybrid-384"


def global_model_configs(
    model: str, short_side: int, gem_p: float, vector: bool, about: str
) -> tuple[PipelineConfig, PipelineConfig]:
    """The two named configurations of a global model added by the user (``app.engine.added_models``), named
    after it: ``model`` (its descriptor alone, as lite2-gem) and ``model``-hybrid (with the default's local
    branch, RootSIFT at 384 px: a feature map is sampled at each keypoint as in lite2-hybrid-384, a vector,
    which has no map to sample, is joined at image level as in hybrid-lite2). ``about`` says what it is."""
    model_fields = dict(global_model=model, cnn_short_side=short_side, gem_p=gem_p)
    if vector:
        model_fields["global_pooling"] = "none"
    alone = PipelineConfig(
        name=model,
        description=f"{about}: its global descriptor alone, PCA-whitened floats",
        local=None,
        codebook=None,
        cnn_global_weight=1.0,
        whiten_power=0.25,
        **model_fields,
    )
    hybrid_fields = {**_HYBRID, "local_long_side": 384}
    if vector:  # image-level hybrid: RootSIFT MBVLAD joined with the vector
        hybrid_fields["cnn_local_weight"] = 0.0
        what = "RootSIFT MBVLAD (384 px) joined with its global vector (image-level hybrid)"
    else:
        what = "RootSIFT (384 px) joined with its map sampled at each keypoint, MBVLAD, joined with the map's GeM"
    hybrid = PipelineConfig(
        name=f"{model}-hybrid",
        description=f"{about}: {what}, PCA-whitened floats",
        **{**hybrid_fields, **model_fields},
    )
    return alone, hybrid


def register_config(config: PipelineConfig) -> None:
    """Add a named configuration (a plug-in's, from its own module, beside its ``app.engine.registry.register``)."""
    CONFIGS[config.name] = config


def configs_serving(mode: str) -> list[str]:
    """The named configurations that can serve search ``mode`` (what a user refused that mode may start)."""
    return [name for name, c in CONFIGS.items() if mode in c.modes]


def get_config(name: str) -> PipelineConfig:
    try:
        return CONFIGS[name]
    except KeyError:
        raise UnknownConfig(f"unknown configuration {name!r}; choose one of {', '.join(CONFIGS)}") from None

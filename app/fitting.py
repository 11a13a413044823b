"""The fitting rules, once, for ``geoloc fit``, ``geoloc refit``, the first start of an empty data dir and the
evaluation: where the SVM bank learns by default, which requests are refused, and how a pipeline and its
bank are fitted against the references.

Why one module: the three faces used to decide these each in their own words, and a rule changed in one
(say, "a configuration without local features has no bank") silently stayed old in the others, so what
the evaluation measured was not what `fit` built.
"""

from __future__ import annotations

from collections.abc import Sequence

from app.engine.configs import PipelineConfig
from app.engine.index.references import ReferenceIndex
from app.engine.pipeline import Features, Pipeline
from app.engine.svm_bank import KINDS, BankParams, SvmBank
from app.engine.training.svm_training import BANK_SOURCES, Geotagged, fit_bank_from, index_of
from app.errors import FitRefused

#: Where an evaluation's bank learns, per fold (never "none": the evaluation's ``svm_bank=off`` says that).
EVAL_BANK_SOURCES = ("train", "collection")


def bank_source(config: PipelineConfig, asked: str | None, train_photos_given: bool = False) -> str:
    """The bank's source: what was asked, else ``train`` when training photos were given apart from the
    references (``refit --train-manifest``), else ``collection`` for a configuration that wants a bank and
    has local features, else ``none``."""
    source = asked or (
        "train" if train_photos_given else "collection" if config.svm_bank and config.local is not None else "none"
    )
    if source not in BANK_SOURCES:
        raise FitRefused(f"--svm-bank must be one of {', '.join(BANK_SOURCES)}, not {source!r}")
    if source != "none" and config.local is None:
        raise FitRefused(f"configuration {config.name} has no local features: an SVM bank has nothing to select")
    return source


def check_bank_kind(kind: str) -> None:
    if kind not in KINDS:
        raise FitRefused(f"--svm-bank-kind must be one of {', '.join(KINDS)}")


def train_bank(
    pipe: Pipeline,
    refs: dict[int, Geotagged],
    train: list[Geotagged],
    source: str,
    kind: str,
    seed: int,
    pos_radius_m: float = 25.0,
    index: ReferenceIndex | None = None,
) -> SvmBank:
    """The bank for ``pipe`` (fitted), retrieved against an in-memory index of ``refs`` encoded by it
    (``index``, when the caller has built it already: the evaluation searches the same one):
    ``collection`` learns from the references (plus ``train``), ``train`` from ``train`` alone."""
    check_bank_kind(kind)
    if source == "train" and not train:
        raise FitRefused(
            "no training photos: --svm-bank train learns from geotagged photos that are not references "
            "(--svm-bank collection learns from the references)"
        )
    if not refs:
        raise FitRefused("no references: the SVM bank needs references to retrieve against")
    if index is None:
        ids = sorted(refs)
        index = index_of(pipe, ids, (refs[i].features for i in ids))
    return fit_bank_from(source, pipe, index, refs, train, BankParams(kind=kind, seed=seed), pos_radius_m=pos_radius_m)


def fit_pipeline(
    pipe: Pipeline,
    features: Sequence[Features],
    refs: dict[int, Geotagged],
    train: Sequence[Geotagged],
    source: str,
    kind: str = "contrastive",
    seed: int = 0,
) -> Pipeline:
    """Fit ``pipe`` (codebook, PCA-whitening, binariser) on ``features`` (every photo it learns from), then,
    unless ``source`` is ``none``, its SVM bank from ``refs`` (the references, by id) and ``train`` (geotagged
    photos that are not references): what `geoloc fit` and the first start of an empty data dir both run."""
    check_bank_kind(kind)
    pipe.fit(list(features), seed=seed)
    if source != "none":
        pipe.bank = train_bank(pipe, refs, list(train), source, kind, seed)
    return pipe

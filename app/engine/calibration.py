"""Know when it does not know: each candidate's ``p_within_25m`` and the confidence rule, fitted on the
user's own collection.

Why on the collection itself: a mapping fitted on penn-campus-gps gave nearly the same high probability to every
query of a small user collection, wrong ones included, and a sizeable one to photos of places the collection
does not hold. So ``geoloc fit`` and ``geoloc refit`` locate a seeded sample of the references against the others
(``app.usecases.fitting.calibrate_collection``): once with the reference's own capture left out (the place is
present, when another capture shows it) and once with every reference within ``absent_radius_m`` removed
(the place is absent). A logistic regression on the evidence (``app.engine.evidence``) of those answers'
candidates gives ``p_within_25m``; the rule then says, from the same sample:

- **confident** when the best ``p_within_25m`` among the candidates of the estimate's group reaches
  ``confident_p``: the lowest threshold at which the sample's confident answers were within 25 m at least
  ``TARGET_PRECISION`` of the time (a pessimistic count) and at most ``MAX_ABSENT_CONFIDENT`` of the absent
  places were confident (never if no threshold does);
- **no_match** ("no reference looks like this photo") when no candidate reaches ``NO_MATCH_P``: what it
  measures is the candidates' look, not the place's absence (a place the collection holds can read so);
- **ambiguous** otherwise.

The estimate itself (``fit_disc``): for every answer, the smallest disc around the fused position that held
the truth for ``RADIUS_RATE`` of the sampled answers with evidence as strong (split-conformal, per bin of
``answer_p``), the absent places counting as answers whose truth lies in no disc at all. An answer has an
estimate when its disc is informative (``Disc.limit_m``: at most ``MAX_RADIUS_M`` and ``MAX_EXTENT_SHARE``
of the collection's extent); the rule above (``confident_p``) then only judges calibrations fitted before
discs.

The sample is counted in captures (a photo and its crops, ``Sample.group``), which answer alike: no
probability exceeds ``max_p`` of the number located (what that many captures, all right, would show at the
90 % lower bound).

Before discs, each confident answer's radius (``stated_radius``) was fitted on the same sample: split-conformal,
per bin of evidence strength, so that the truth lies within it for ``RADIUS_RATE`` of such answers
(``fit_radius``); a calibration too small for a disc keeps that rule.

A collection too small to calibrate (fewer than ``MIN_QUERIES`` sampled references, or fewer than
``MIN_POSITIVES`` right candidates among their answers) gets ``conservative()``: no probabilities at all,
and confident only when at least ``CONSERVATIVE_SUPPORT`` candidates agree on one spot holding
``CONSERVATIVE_SHARE`` of the weight. It never falls back to another collection's figures.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from app.engine.artifacts import atomic_write_bytes
from app.engine.estimate import RADIUS_FLOOR_M, Estimate
from app.engine.evidence import Evidence

CALIBRATION_FILE = "calibration.json"
FORMAT = 1

TARGET_PRECISION = 0.9
MAX_ABSENT_CONFIDENT = 0.01
NO_MATCH_P = 0.1
MIN_QUERIES = 16
MIN_POSITIVES = 3
#: The weight of each absent sample against a present one: places not in the collection are as common as
#: places in it, for all the rule knows.
ABSENT_WEIGHT = 1.0
#: L2 regularisation of the logistic regression (sklearn's C): strong, since small collections give few
#: right candidates.
C = 0.5
CONSERVATIVE_SUPPORT = 3
CONSERVATIVE_SHARE = 0.8
#: A calibration judges a collection that holds at least this share of the references it located.
SAME_COLLECTION_SHARE = 0.5
#: About how many references (photos and crops, several per place) a collection needs before its own
#: calibration finds a level at which answers are confident: measured on penn-campus-gps by refitting
#: subsets of whole captures (``python -m bench.calibration_size``, docs/results.md): refits of a hundred
#: or so references found none, refits of a few hundred did.
CONFIDENT_FROM_REFERENCES = 300
#: The share of confident answers whose truth lies within the stated radius: what the answer states.
RADIUS_RATE = 0.9
#: The fewest sampled answers a bin of evidence strength holds (fewer merge into a neighbour): with 30, the
#: conformal quantile at 90 % is the 28th smallest error, and the bin's coverage lies between 90 % and 93 %
#: in expectation (split-conformal's 1/(n+1)); fewer and one unlucky error moves the radius a lot.
MIN_BIN_SAMPLES = 30
#: At most this many bins (quartiles of the evidence strength): the evaluation reports the weakest quartile.
RADIUS_BINS = 4
#: The disc (``fit_disc``): a bin of evidence strength holds at least this many answers (with 25, the
#: conformal quantile at 90 % is the 24th smallest error: one more unlucky error moves it by one rank, not
#: past the end), and enough captures that one of them may fail (``disc_bin_captures``).
MIN_DISC_BIN = 25
#: An answer has an estimate only when its disc is at most this wide (``Settings.max_radius_m``' default;
#: docs/disc.md says how it was chosen) ...
MAX_RADIUS_M = 100.0
#: ... and at most this share of the collection's extent (a disc as wide as the collection says nothing).
MAX_EXTENT_SHARE = 0.25
#: The z of the one-sided lower confidence bound (90 %) that caps every stated probability (``max_p``):
#: with n captures all right, the bound is n / (n + z^2), as if 1.64 wrong captures were added.
CEILING_Z = 1.2816

# The reason codes a client can branch on (documented in docs/api.md and in /locate's schema).
NO_FEATURES = "no_features"
NO_REFERENCES = "no_references"
NO_MATCH = "no_match"
#: How a no_match reason begins: what was measured, never that the place is absent.
NO_MATCH_WORDS = "no reference looks like this photo: "
AMBIGUOUS = "ambiguous"


@dataclass(frozen=True)
class Decision:
    """What the rule says of one answer: confident or the reason code and words, and the candidates'
    probabilities (None where the collection could not be calibrated)."""

    confident: bool
    code: str | None
    reason: str | None
    p_within: np.ndarray | None
    answer_p: float | None  # the best p among the estimate's group: what the confident threshold reads
    #: A confident answer's radius and the rate at which it holds, fitted on the collection (``stated_radius``);
    #: None: the estimate's own (the constant rule, ``fuse_position``), not calibrated.
    radius_m: float | None = None
    radius_rate: float | None = None


@dataclass
class Sample:
    """One sampled answer: its candidates' evidence, whether each lies within 25 m of the truth, which ones
    the estimate fused into its group, whether the estimate lies within 25 m, and how far it lies from the truth
    (what the stated radius is fitted on)."""

    evidence: Evidence
    within: np.ndarray
    members: np.ndarray
    estimate_within: bool
    absent: bool
    error_m: float | None = None
    #: The capture (a photo and its crops) the located reference belongs to: answers of one capture are not
    #: independent, so the rule counts its support in captures (``max_p``).
    group: str | None = None


@dataclass(frozen=True)
class Disc:
    """The disc an answer states (``fit_disc``): per bin of evidence strength (``basis``: ``answer_p``; inner
    edges ``edges``, ascending), the radius within which the truth lay for ``rate`` of the ``n`` sampled
    answers of that bin (None: no finite radius did: too many of them were of places removed from the
    collection, or far off), and ``limit_m``, the widest disc that counts as an estimate
    (``min(max_radius_m, MAX_EXTENT_SHARE * extent_m)``)."""

    rate: float
    edges: list[float]
    radius_m: list[float | None]
    n: list[int]
    limit_m: float
    max_radius_m: float
    extent_m: float | None = None
    basis: str = "answer_p"

    def radius(self, strength: float) -> float | None:
        """The disc of an answer this strong (None: none holds at ``rate``)."""
        return self.radius_m[int(np.searchsorted(np.asarray(self.edges, float), strength, side="right"))]

    def estimate_radius(self, strength: float) -> float | None:
        """The disc of an answer this strong when it is informative (at most ``limit_m``), else None."""
        r = self.radius(strength)
        return r if r is not None and r <= self.limit_m else None

    @property
    def informative_anywhere(self) -> bool:
        return any(r is not None and r <= self.limit_m for r in self.radius_m)


@dataclass
class Calibration:
    names: tuple[str, ...] = ()
    mean: list[float] = field(default_factory=list)
    scale: list[float] = field(default_factory=list)
    #: The range of each column in the calibration sample: evidence beyond it (a photo that IS a reference
    #: scores 1.0, far above anything the sample saw) is read at the edge, never extrapolated.
    low: list[float] = field(default_factory=list)
    high: list[float] = field(default_factory=list)
    coef: list[float] = field(default_factory=list)
    intercept: float = 0.0
    confident_p: float = 1.01
    no_match_p: float = NO_MATCH_P
    source: str = "conservative"  # "collection": fitted on the collection; "conservative": too small
    note: str = ""
    report: dict = field(default_factory=dict)
    #: The rule for verified answers (``rerank``), fitted on the same sample located with verification, as a
    #: nested ``Calibration``'s fields; None when the fit did not verify (``--calibrate-rerank``): verified
    #: answers then read this rule's global columns only.
    verified: dict | None = None
    #: The sha256 of each reference photo the calibration located: what tells a data dir whether these
    #: figures are its own (``for_collection``).
    references: list[str] = field(default_factory=list)
    #: The stated radius (``fit_radius``): ``rate``, ``basis`` (the evidence strength the bins read:
    #: ``answer_p``), ``edges`` (the bins' inner edges, ascending), ``radius_m`` and ``n`` per bin, and
    #: ``population`` (the sampled answers it was fitted on). None: the constant rule (a conservative
    #: collection, too few sampled answers, or a calibration fitted before stated radii).
    radius: dict | None = None
    #: The disc every answer states (``fit_disc``, ``Disc``'s fields); None: fitted before discs (the
    #: ``confident_p`` rule and ``radius`` then), or too few sampled answers to fit one.
    disc: dict | None = None
    #: The highest probability this calibration states (``max_p``): what its sample of captures can support.
    #: 1.0 in a calibration fitted before it.
    ceiling: float = 1.0
    #: The disc a photo of a sequence states (``Disc``'s fields, ``basis`` ``sequence_p``: the sequence's
    #: posterior of the place), fitted on the collection's references arranged as held-out walks
    #: (``app.usecases.walk_calibration``); None: no references with capture times, too few of them, or a
    #: calibration fitted before it (a sequence's answers then read the single-photo disc, their rate unstated).
    sequence_disc: dict | None = None

    @classmethod
    def conservative(cls, note: str, report: dict | None = None) -> Calibration:
        return cls(source="conservative", note=note, report=report or {})

    @property
    def calibrated(self) -> bool:
        return self.source == "collection"

    def for_collection(self, present: int) -> Calibration:
        """This rule, when the collection holds at least ``SAME_COLLECTION_SHARE`` of the ``references`` it was
        fitted on (``present`` of them); else the conservative rule, saying why.

        Why: a data dir that reads the models dir's pipeline (any ``geoloc ingest --data-dir D``) used to be
        judged by the demo collection's figures: penn photos read "not in this collection" for a
        candidate at the very spot they were taken. A collection is judged by its own calibration or by none."""
        if not self.calibrated:
            return self
        if not self.references:
            return Calibration.conservative(
                "this pipeline's calibration does not record which collection it was fitted on (fitted before "
                "it did): run `geoloc refit` to calibrate this collection on its own references"
            )
        if present >= SAME_COLLECTION_SHARE * len(self.references):
            return self
        return Calibration.conservative(
            f"the pipeline's calibration was fitted on another collection ({present} of the "
            f"{len(self.references)} references it located are in this one): run `geoloc refit` to calibrate "
            "this collection on its own references"
        )

    def confidence_note(self, references: int) -> str | None:
        """What a collection that cannot give a confident answer yet needs (None when it can): the refit
        summary and /ready say it, so that a small collection's answers are not read as a fault."""
        if self.disc is not None:
            small = not Disc(**self.disc).informative_anywhere
        else:
            small = self.report.get("too_small") or (self.calibrated and self.confident_p > 1.0)
        if not small:
            return None
        return (
            f"no answer can be confident in this collection yet: it needs about {CONFIDENT_FROM_REFERENCES} "
            f"references (it has {references}), several of each place, then `geoloc refit`"
        )

    def for_answer(self, verified: bool) -> Calibration:
        """The rule that reads this answer's evidence: the verified one for a verified answer, when the
        collection was calibrated with verification; else this one."""
        if not verified or not self.verified:
            return self
        return Calibration(**{**self.verified, "names": tuple(self.verified["names"])})

    # -- applying -------------------------------------------------------------------------------------
    def probabilities(self, evidence: Evidence) -> np.ndarray | None:
        if not self.calibrated:
            return None
        x = evidence.columns(self.names)
        if self.low and self.high:
            x = np.clip(x, np.asarray(self.low), np.asarray(self.high))
        x = (x - np.asarray(self.mean)) / np.asarray(self.scale)
        z = x @ np.asarray(self.coef) + self.intercept
        return np.minimum(1.0 / (1.0 + np.exp(-z)), self.ceiling)

    def decide(self, evidence: Evidence, estimate: Estimate) -> Decision:
        if estimate.lat is None or len(evidence.values) == 0:
            return Decision(False, NO_REFERENCES, estimate.reason or "no candidates", None, None)
        p = self.probabilities(evidence)
        members = np.zeros(len(evidence.values), bool)
        m = np.asarray(estimate.members, bool)[: len(members)]
        members[: len(m)] = m
        if p is None:
            strong = estimate.support >= CONSERVATIVE_SUPPORT and estimate.confidence >= CONSERVATIVE_SHARE
            if strong:
                return Decision(True, None, None, None, None)
            return Decision(
                False,
                AMBIGUOUS,
                f"uncalibrated: {self.note}; only {CONSERVATIVE_SUPPORT} or more candidates agreeing on one spot "
                f"count as confident, and the best group has {estimate.support} holding {estimate.confidence:.0%} "
                "of the weight",
                None,
                None,
            )
        answer_p = float(p[members].max()) if members.any() else float(p.max())
        stated = self.estimate_disc(answer_p, estimate.radius_m)
        if stated is not None:
            return Decision(True, None, None, p, answer_p, *stated)
        best = float(p.max())
        top, seen = self._beyond_range(evidence)
        if top is not None:
            # Clipped to the sample's edge, the probabilities say nothing of such a match: never "not here".
            return Decision(
                False,
                AMBIGUOUS,
                f"the best match scores {top:.3f}, above anything this collection's calibration saw ({seen:.3f}): "
                "it may be the same photo as a reference; compare them",
                p,
                answer_p,
            )
        if best < self.no_match_p:
            return Decision(
                False,
                NO_MATCH,
                f"{NO_MATCH_WORDS}no candidate has a {self.no_match_p:.0%} chance of lying "
                f"within 25 m of where it was taken (best {best:.0%})",
                p,
                answer_p,
            )
        if self.disc is not None:
            return Decision(False, AMBIGUOUS, disc_reason(Disc(**self.disc), answer_p), p, answer_p)
        if self.confident_p > 1.0:
            needs = (
                "and no answer of this collection is confident: its calibration found no level at which its own "
                "confident answers held (too few references of the same places); add some, then `geoloc refit`"
            )
        else:
            needs = f"below the {self.confident_p:.1%} this collection needs for a confident answer"
        return Decision(
            False,
            AMBIGUOUS,
            f"the best group's chance of lying within 25 m is {answer_p:.1%}, {needs}",  # the code says ambiguous
            p,
            answer_p,
        )

    def estimate_disc(
        self, answer_p: float, constant_m: float | None = None
    ) -> tuple[float | None, float | None] | None:
        """Whether evidence this strong gets an estimate, and with which disc: (radius, rate) where it does,
        (None, None) for the constant rule's radius, None where it does not. The fitted disc (``fit_disc``)
        where the collection has one: its radius at its rate, where that is small enough to inform; else
        the confident threshold (``confident_p``) and its stated radius. The rule for a photo alone, and for a
        photo in a library's run or in a sequence of a collection without a disc of its own for sequences
        (``sequence_disc``)."""
        if self.disc is not None:
            disc = Disc(**self.disc)
            radius = disc.estimate_radius(answer_p)
            return None if radius is None else (radius, disc.rate)
        if answer_p >= self.confident_p:
            return self.stated_radius(answer_p, constant_m)
        return None

    def stated_radius(self, answer_p: float, constant_m: float | None = None) -> tuple[float | None, float | None]:
        """A confident answer's radius and its rate: the conformal radius of its evidence bin (``fit_radius``),
        never below ``RADIUS_FLOOR_M`` nor below ``constant_m`` (the constant rule's radius for this answer,
        ``fuse_position``'s); (None, None) without a fitted radius (the constant rule alone then).

        Why never below the constant rule: the calibration's sample is easier than real queries (its Brier
        score is well below the held-out queries'; it locates the collection's own references under an SVM
        bank trained on them), so its conformal radii alone held for clearly fewer confident answers than the
        ``RADIUS_RATE`` stated (docs/results.md). The larger of the two held for more than it; the conformal
        radius widens an answer whose bin's errors are larger than the rule's."""
        r = self.radius
        if not r:
            return None, None
        k = int(np.searchsorted(np.asarray(r["edges"], float), answer_p, side="right"))
        return max(float(r["radius_m"][k]), RADIUS_FLOOR_M, constant_m or 0.0), float(r["rate"])

    @property
    def radius_note(self) -> str:
        """How answers' radii are chosen, in words (the refit summary says it)."""
        if self.disc:
            d = Disc(**self.disc)
            shown = [f"{r:.0f}" if r is not None else "none" for r in d.radius_m]
            return (
                f"discs of {', '.join(shown)} m by evidence strength, each holding for "
                f"{d.rate * 100:.0f} % of {sum(d.n)} sampled answers; an estimate for those within {d.limit_m:.0f} m"
            )
        if self.radius:
            radii = ", ".join(f"{x:.0f}" for x in self.radius["radius_m"])
            return (
                f"stated radii {radii} m by evidence strength, each holding for {self.radius['rate'] * 100:.0f} % of "
                f"{self.radius['population']} sampled answers"
            )
        return "radii by the constant rule (farthest fused candidate + 40 m), their rate not calibrated"

    def _beyond_range(self, evidence: Evidence) -> tuple[float | None, float]:
        """The best score when it lies above the calibration sample's highest (a photo that is a reference,
        or a near copy: the sample never holds one), else None."""
        if "best_score" not in self.names or not self.high or not len(evidence.values):
            return None, 0.0
        seen = float(self.high[self.names.index("best_score")])
        top = float(evidence.columns(("best_score",))[0, 0])
        return (top, seen) if top > seen else (None, seen)

    # -- persistence ----------------------------------------------------------------------------------
    def save(self, directory: Path) -> None:
        data = {"format": FORMAT, **asdict(self)}
        atomic_write_bytes(Path(directory) / CALIBRATION_FILE, json.dumps(data, indent=1).encode())

    @classmethod
    def load(cls, directory: Path) -> Calibration:
        path = Path(directory) / CALIBRATION_FILE
        if not path.exists():
            return cls.conservative("this pipeline was fitted before calibration existed: run `geoloc refit`")
        data = json.loads(path.read_text())
        if data.pop("format", None) != FORMAT:
            return cls.conservative(f"{path} has another format: run `geoloc refit`")
        data["names"] = tuple(data["names"])
        if data.get("source") == "collection" and "radius" not in data:
            data["note"] = (
                data.get("note", "") + "; fitted before stated radii: confident answers keep the constant rule's "
                "radius, its rate not calibrated (`geoloc refit` fits them)"
            )
        if data.get("source") == "collection" and "disc" not in data:
            data["note"] = (
                data.get("note", "") + "; fitted before discs: answers are judged by the confident threshold "
                "(`geoloc refit` fits the disc every answer states)"
            )
        if data.get("verified"):
            data["verified"]["names"] = tuple(data["verified"]["names"])
        return cls(**data)


def disc_reason(disc: Disc, answer_p: float) -> str:
    """Why an answer this strong has no estimate, in words that claim only what the calibration measured."""
    share = f"{rate_words(disc.rate)} such answers"
    r = disc.radius(answer_p)
    if r is None:
        return (
            f"no disc holds {share} (evidence strength {answer_p:.0%}): of this collection's own answers this weak, "
            f"more than {rate_words(1 - disc.rate)} were of places removed from it, or far off"
        )
    return (
        f"{share} (evidence strength {answer_p:.0%}) lie within {r:.0f} m, wider than the {disc.limit_m:.0f} m an "
        "estimate may state"
    )


def rate_words(rate: float) -> str:
    """A rate as a count a reader pictures: 0.9 -> "9 in 10" (the CLI and the page say it alike)."""
    for of in (10, 20, 100):
        if abs(rate * of - round(rate * of)) < 1e-6:
            return f"{round(rate * of)} in {of}"
    return f"{rate:.0%}"


# -- fitting ----------------------------------------------------------------------------------------------
def fit_calibration(
    samples: list[Sample],
    seed: int = 0,
    rate: float = RADIUS_RATE,
    max_radius_m: float = MAX_RADIUS_M,
    extent_m: float | None = None,
) -> Calibration:
    """The logistic regression and the thresholds from the sampled answers (present and absent), and the disc
    every answer states (``fit_disc``: at ``rate``, an estimate up to ``max_radius_m`` and a share of the
    collection's ``extent_m``)."""
    from sklearn.linear_model import LogisticRegression

    present = [s for s in samples if not s.absent]
    positives = int(sum(int(s.within.sum()) for s in present))
    report = {
        "present": len(present),
        "absent": len(samples) - len(present),
        "right_candidates": positives,
        "candidates": int(sum(len(s.within) for s in samples)),
    }
    if len(present) < MIN_QUERIES or positives < MIN_POSITIVES:
        return Calibration.conservative(
            f"the collection is too small to calibrate ({len(present)} references sampled, {positives} right "
            f"candidates among their answers; at least {MIN_QUERIES} and {MIN_POSITIVES} needed)",
            {**report, "too_small": True},
        )
    names = samples[0].evidence.names
    x = np.vstack([s.evidence.columns(names) for s in samples if len(s.within)])
    y = np.concatenate([s.within for s in samples]).astype(int)
    w = np.concatenate([np.full(len(s.within), ABSENT_WEIGHT if s.absent else 1.0) for s in samples])
    mean, scale = x.mean(axis=0), x.std(axis=0)
    scale[scale < 1e-9] = 1.0
    model = LogisticRegression(C=C, max_iter=1000, random_state=seed)
    model.fit((x - mean) / scale, y, sample_weight=w)
    cal = Calibration(
        names=tuple(names),
        mean=mean.tolist(),
        scale=scale.tolist(),
        low=x.min(axis=0).tolist(),
        high=x.max(axis=0).tolist(),
        coef=model.coef_[0].tolist(),
        intercept=float(model.intercept_[0]),
        source="collection",
        report=report,
    )
    captures = len({capture(s) for s in present})
    cal.ceiling = max_p(captures)
    report["captures"] = captures
    report["max_p"] = round(cal.ceiling, 4)
    cal.confident_p = choose_threshold(cal, samples)
    absent_best = [float(p.max()) for s in samples if s.absent and len(p := cal.probabilities(s.evidence))]
    cal.report.update(
        {
            "confident_p": round(cal.confident_p, 4),
            "brier": round(brier(cal, samples), 4),
            "mean_best_p_absent": round(float(np.mean(absent_best or [0.0])), 4),
        }
    )
    if all(s.absent or s.error_m is not None for s in samples):
        strength = np.array([answer_probability(cal, s) for s in samples])
        errors = np.array([np.inf if s.absent else s.error_m for s in samples])
        # A capture's answers with its place present, and those with it removed, are two experiments.
        groups = [(capture(s), s.absent) for s in samples]
        disc = fit_disc(strength, errors, groups, rate, max_radius_m, extent_m)
        cal.disc = asdict(disc) if disc is not None else None
    if cal.disc is None:  # too few answers for a disc, or samples without errors: the confident threshold
        cal.radius = fit_radius(cal, samples)
    cal.note = f"fitted on {len(present)} references of this collection; {cal.radius_note}"
    return cal


def fit_disc(
    strength: np.ndarray,
    errors: np.ndarray,
    groups: Sequence[object] | None = None,
    rate: float = RADIUS_RATE,
    max_radius_m: float = MAX_RADIUS_M,
    extent_m: float | None = None,
    floor_m: float = RADIUS_FLOOR_M,
    min_captures: int | None = None,
    min_n: int = MIN_DISC_BIN,
) -> Disc | None:
    """The smallest disc around the estimate that holds the truth for ``rate`` of the answers, conditional on
    the evidence strength: split-conformal per bin of ``strength``, the conformal quantile (the
    ceil((n + 1) * rate)-th smallest) of the bin's ``errors`` (metres from the estimate to the truth; ``inf``
    for a place removed from the collection: no disc holds it), never below ``floor_m``. None when fewer than
    ``min_n`` answers.

    ``groups`` (each answer's capture: a photo and its crops; every answer its own when None): the quantile
    is counted in captures, each capture of a bin counting once with its worst error there. Why: a capture's
    answers fail together (its crops show the same facade, matched to the same look-alike across the
    street), so counted one by one they make a bin look surer than its captures allow (docs/disc.md). A bin
    of too few captures for a conformal quantile at ``rate`` (fewer than 9 at 90 %) states no disc.

    The bins (``disc_bins``) are cut from the strongest answer down, each closing once it holds
    ``min_captures`` captures (by default ``disc_bin_captures(rate)``, the fewest whose quantile at ``rate``
    survives one capture far off: 19 at 90 %) and ``min_n`` answers. Why by captures, not quantiles of
    answers: a bin's quantile is only as steady as its number of captures; with the fewest a quantile needs,
    one look-alike among them left the bin with no disc at all, and with it (monotone) every weaker bin.
    Monotone by pooling adjacent violators: where a stronger bin states a wider disc than its weaker
    neighbour, the two are one bin, refitted, until stronger evidence never states a wider disc. Why pooling
    and not the running maximum: the maximum let one unlucky strong bin widen every weaker bin to its radius
    (or to none), where pooling spends that bin's failure on the captures beside it.

    Why conditional: one disc for all answers holds on average and not for the weak ones; "9 in 10" must
    hold for answers like the one at hand. Why the absent places among them: a disc is then stated only where
    the evidence says the place is held, and evidence that places removed from the collection also reach
    gets no finite disc at all."""
    strength, errors = np.asarray(strength, float), np.asarray(errors, float)
    groups = list(range(len(strength))) if groups is None else list(groups)
    if len(strength) < max(min_n, 1) or conformal_radius(errors, rate) is None:
        return None
    if min_captures is None:
        min_captures = disc_bin_captures(rate)
    blocks = disc_bins(strength, groups, min_captures, min_n)  # strongest first
    radii = [_block_radius(errors, groups, b, rate) for b in blocks]
    k = 0
    while k < len(blocks) - 1:
        if radii[k] > radii[k + 1]:  # a violator: pool, refit, and look again at the stronger neighbour
            blocks[k : k + 2] = [np.concatenate(blocks[k : k + 2])]
            radii[k : k + 2] = [_block_radius(errors, groups, blocks[k], rate)]
            k = max(k - 1, 0)
        else:
            k += 1
    blocks, radii = blocks[::-1], np.maximum(radii[::-1], floor_m)  # weakest first, as ``Disc`` reads them
    limit = min(max_radius_m, MAX_EXTENT_SHARE * extent_m) if extent_m else max_radius_m
    return Disc(
        rate=rate,
        # Each inner edge is the weakest strength of the bin above it (unrounded: an answer tied with an edge
        # reads the bin it was fitted in; one between two bins' strengths reads the weaker bin's disc).
        edges=[float(strength[b].min()) for b in blocks[1:]],
        radius_m=[round(float(r), 1) if np.isfinite(r) else None for r in radii],
        n=[len(b) for b in blocks],
        limit_m=round(float(limit), 1),
        max_radius_m=float(max_radius_m),
        extent_m=None if extent_m is None else round(float(extent_m), 1),
    )


def disc_bin_captures(rate: float) -> int:
    """The fewest captures whose conformal quantile at ``rate`` is not their worst error: the smallest n with
    ceil((n + 1) * rate) <= n - 1, so that one capture of a bin may lie far off (or be of a place removed
    from the collection) and the bin still states a disc (19 at 90 %, 39 at 95 %)."""
    n = 2
    while int(np.ceil((n + 1) * rate - 1e-9)) > n - 1:
        n += 1
    return n


def disc_bins(strength: np.ndarray, groups: Sequence[object], min_captures: int, min_n: int) -> list[np.ndarray]:
    """The answers' indices cut into bins from the strongest down, each closing once it holds ``min_captures``
    distinct ``groups`` and ``min_n`` answers; answers of equal strength stay in one bin, and what is left
    at the weak end joins the last bin."""
    order = np.argsort(-np.asarray(strength, float), kind="stable")
    bins: list[np.ndarray] = []
    start, seen = 0, set()
    for pos, i in enumerate(order):
        seen.add(groups[i])
        tied = pos + 1 < len(order) and strength[order[pos + 1]] == strength[i]
        if not tied and len(seen) >= min_captures and pos + 1 - start >= min_n:
            bins.append(order[start : pos + 1])
            start, seen = pos + 1, set()
    if start < len(order):
        rest = order[start:]
        bins[-1:] = [np.concatenate([bins[-1], rest])] if bins else [rest]
    return bins


def _block_radius(errors: np.ndarray, groups: Sequence[object], block: np.ndarray, rate: float) -> float:
    """A bin's conformal radius over its captures' worst errors; inf when none holds."""
    r = _capture_radius(errors[block], [groups[i] for i in block], rate)
    return np.inf if r is None else r


def _capture_radius(errors: np.ndarray, groups: Sequence[object], rate: float) -> float | None:
    worst: dict[object, float] = {}
    for x, g in zip(errors, groups, strict=True):
        worst[g] = max(worst.get(g, 0.0), float(x))
    return conformal_radius(np.array(list(worst.values())), rate)


def capture(s: Sample) -> object:
    """What tells the sample's captures apart: its group, else the answer itself (every answer its own)."""
    return s.group if s.group is not None else id(s)


def max_p(captures: float, z: float = CEILING_Z) -> float:
    """The highest probability a calibration that located ``captures`` captures (place present) states: the
    lower end of the one-sided Wilson interval (``z``) had every one of them been right, n / (n + z^2).

    Why: the logistic regression extrapolates from few captures with the confidence of many: a small
    collection stated a near-certain probability for an answer hundreds of metres off. A probability cannot
    say more than the collection's own sample could show, and a small sample shows less: 0.87 from 11
    captures, 0.976 from the 68 of penn-campus-gps (whose confident threshold lies below)."""
    return float(captures / (captures + z * z)) if captures > 0 else 0.0


def conformal_radius(errors: np.ndarray, rate: float = RADIUS_RATE) -> float | None:
    """Split-conformal: the ceil((n + 1) * rate)-th smallest of ``n`` errors, within which a new answer drawn
    like them lies at least ``rate`` of the time; None when n is too small for one (n + 1 < 1 / (1 - rate))."""
    errors = np.sort(np.asarray(errors, float))
    k = int(np.ceil((len(errors) + 1) * rate - 1e-9))
    return float(errors[k - 1]) if 0 < k <= len(errors) else None


def strength_bins(strength: np.ndarray, bins: int = RADIUS_BINS, min_n: int = MIN_BIN_SAMPLES) -> list[float]:
    """The inner edges of up to ``bins`` bins of ``strength``, at its quantiles, each holding at least
    ``min_n`` values: a bin with fewer (ties at an edge) merges into its smaller neighbour."""
    strength = np.asarray(strength, float)
    k = max(1, min(bins, len(strength) // max(min_n, 1)))
    edges = sorted(set(np.quantile(strength, np.arange(1, k) / k).tolist()))
    while edges:
        counts = np.bincount(np.searchsorted(edges, strength, side="right"), minlength=len(edges) + 1)
        j = int(np.argmin(counts))
        if counts[j] >= min_n:
            break
        # Drop the edge between bin j and its smaller neighbour.
        if j == 0 or (j < len(edges) and counts[j + 1] < counts[j - 1]):
            del edges[j]
        else:
            del edges[j - 1]
    return edges


def fit_radius(cal: Calibration, samples: list[Sample], rate: float = RADIUS_RATE) -> dict | None:
    """The stated radius, per bin of evidence strength, from the sample's answers whose place is present.

    Why per bin: one radius for all confident answers holds on average but not for the weak ones (their
    errors are larger), and "9 in 10" must hold for the answer at hand. The strength is ``answer_p``, the
    calibrated chance that the estimate's group lies within 25 m: what the confident threshold reads (so the
    bins nest with the decision), continuous (unlike the group's support, 1-10), and it weighs every column
    of the evidence the collection learnt. The radius is fitted on the answers that were confident when at
    least ``MIN_BIN_SAMPLES`` were (the population a radius is stated for), else on every present answer
    (their errors are larger: a wider radius, never a narrower one). None when even those are too few."""
    present = [s for s in samples if not s.absent and s.error_m is not None]
    p = np.array([answer_probability(cal, s) for s in present])
    err = np.array([s.error_m for s in present])
    confident = p >= cal.confident_p
    population = "confident" if confident.sum() >= MIN_BIN_SAMPLES else "present"
    if population == "confident":
        p, err = p[confident], err[confident]
    if conformal_radius(err, rate) is None:
        return None
    edges = strength_bins(p)
    bin_of = np.searchsorted(edges, p, side="right")
    radii = [conformal_radius(err[bin_of == k], rate) for k in range(len(edges) + 1)]
    if any(r is None for r in radii):  # never with MIN_BIN_SAMPLES >= 9; the whole sample's then
        edges, radii = [], [conformal_radius(err, rate)]
    return {
        "rate": rate,
        "basis": "answer_p",
        "edges": [round(x, 6) for x in edges],
        "radius_m": [round(float(r), 1) for r in radii],
        "n": np.bincount(bin_of, minlength=len(edges) + 1).tolist() if edges else [len(err)],
        "population": population,
    }


def answer_probability(cal: Calibration, s: Sample) -> float:
    p = cal.probabilities(s.evidence)
    if p is None or len(p) == 0:
        return 0.0
    return float(p[s.members].max()) if s.members.any() else float(p.max())


def choose_threshold(cal: Calibration, samples: list[Sample]) -> float:
    """The lowest answer probability at which the sample's confident answers are right at least
    ``TARGET_PRECISION`` of the time, counted pessimistically (one wrong answer added), with at most
    ``MAX_ABSENT_CONFIDENT`` of the absent places confident; 1.01 (never confident) when none is."""
    scored = sorted(((answer_probability(cal, s), s) for s in samples), key=lambda t: -t[0])
    n_absent = max(1, sum(s.absent for s in samples))
    best = 1.01
    hits = n = absent = 0
    for k, (p, s) in enumerate(scored):
        n += 1
        hits += int(s.estimate_within and not s.absent)
        absent += int(s.absent)
        if k + 1 < len(scored) and scored[k + 1][0] == p:
            continue  # ties go together
        if hits / (n + 1) >= TARGET_PRECISION and absent / n_absent <= MAX_ABSENT_CONFIDENT:
            best = p
    return float(best)


def brier(cal: Calibration, samples: list[Sample]) -> float:
    ps, ys = [], []
    for s in samples:
        p = cal.probabilities(s.evidence)
        if p is not None and len(p):
            ps.append(p)
            ys.append(s.within)
    if not ps:
        return float("nan")
    return float(np.mean((np.concatenate(ps) - np.concatenate(ys).astype(float)) ** 2))


def reliability(p: np.ndarray, y: np.ndarray, edges=(0.0, 0.1, 0.2, 0.3, 0.5, 0.7, 1.0001)) -> list[dict]:
    """Predicted against observed, per bin of predicted probability (the evaluation's reliability table)."""
    p, y = np.asarray(p, float), np.asarray(y, float)
    out = []
    for lo, hi in zip(edges[:-1], edges[1:], strict=True):
        m = (p >= lo) & (p < hi)
        if m.any():
            out.append(
                {
                    "bin": f"{lo:.1f}-{min(hi, 1.0):.1f}",
                    "n": int(m.sum()),
                    "predicted": round(float(p[m].mean()), 3),
                    "observed": round(float(y[m].mean()), 3),
                }
            )
    return out

"""The run record: every option of a sequence run that affects its results, one frozen object per kind.

:class:`TrackOptions` (2-D sequences: :func:`dic.sequence.track_sequence`, ``specula track``) and
:class:`StereoOptions` (stereo sequences: :func:`dic.sequence.stereo_sequence`, ``specula stereo``)
hold each option with its default written out. They are validated once, when built (with
:mod:`kernels.checks`; a bad value raises :class:`OptionError`, a ``ValueError`` that names the
option), by the library and the command line alike, so that both build the same record for the
same run. Derived defaults are resolved (``step`` None -> ``subset // 2`` for 2-D and stereo grids,
``check_outliers`` None -> on unless ``robust`` is False), and options that cannot act are written ``None``
(``search_radius`` without ``search``, ``auto_valid``/``auto_zncc`` unless ``reference="auto"``),
so two records of the same run are equal whichever way they were written.

A record is stored in a result file's ``/settings`` (docs/results_format.md, "Settings") by
:meth:`~TrackOptions.to_settings`: every option with its value and ``"options_schema": 2``; POIs
given as an array are stored as a digest (``{"shape", "sha256"}``), a region of interest in its
JSON form (:meth:`dic.correlation.points.Region.settings`). :meth:`~TrackOptions.from_settings`
reads it back, and also reads the settings written before the record (schema 1: Specula 8d9f975
and earlier; for 2-D both the command line's form, where ``search`` was the radius and
``search_method`` the method, and the library's, which held only the keywords given; for stereo
the keywords given). Resuming compares records (:meth:`~TrackOptions.resume_check`): an explicit
default is the default, and a real difference is refused with the differing options named by
their keyword and command-line option.
"""
from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass, field, fields, replace
from typing import Any, ClassVar

import numpy as np

from kernels.checks import boolean, in_range, non_negative_int, odd_int, positive_float, positive_int

from ..correlation.subset_masks import check_min_kept_fraction, check_subset_mask
from .reference import AUTO_VALID, AUTO_ZNCC, parse_reference
from .verification import VERIFY_SPREAD, VERIFY_ZNCC, check_verify_spread

__all__ = ["OPTIONS_SCHEMA", "OptionError", "TrackOptions", "StereoOptions"]

#: the version of the settings record written by :meth:`TrackOptions.to_settings` (schema 1: before the record)
OPTIONS_SCHEMA = 2
_SCHEMA_KEY = "options_schema"
#: IC-GN iterations per point at most (kernels.icgn.MAX_ITER, not imported here: that module loads Warp)
_MAX_ITER = 10000
#: the 2-D settings key of the image scale: dic.postprocess.SCALE_KEY (tests/dic/test_run_options.py keeps them equal)
_SCALE_KEY = "scale_mm_per_px"


class OptionError(ValueError):
    """A run option with a bad value; :attr:`option` is its keyword (e.g. ``"max_iter"``)."""

    def __init__(self, option: str, message: str):
        super().__init__(message)
        self.option = option


def _checked(option: str, check, *args, **kwargs):
    """``check(*args, **kwargs)`` (a :mod:`kernels.checks` function), its ValueError as an :class:`OptionError`."""
    try:
        return check(*args, **kwargs)
    except OptionError:
        raise
    except ValueError as exc:
        raise OptionError(option, str(exc)) from None


def _points_digest(points) -> dict:
    """The stored form of explicit POIs: shape and SHA-256 of their float64 coordinates (not the coordinates:
    millions of POIs would bloat the file's header)."""
    pts = np.ascontiguousarray(np.asarray(points, dtype=np.float64))
    return {"shape": list(pts.shape), "sha256": hashlib.sha256(pts.tobytes()).hexdigest()}


def _points(value) -> tuple[dict | None, np.ndarray | None]:
    """POIs as given (array) or stored (digest dict, or the coordinate list of schema-1 stereo files)."""
    from kernels.checks import as_points

    if value is None:
        return None, None
    if isinstance(value, dict):
        if set(value) != {"shape", "sha256"}:
            raise OptionError("points", f"points must be an (N, 2) array of (x, y) px, got {value!r}")
        return {"shape": [int(n) for n in value["shape"]], "sha256": str(value["sha256"])}, None
    arr = _checked("points", as_points, value)
    return _points_digest(value), arr


def _roi(value, shape) -> tuple[Any, Any]:
    """A region of interest: a :class:`~dic.correlation.points.Region`, its stored JSON form, or (with the
    image ``shape``) any form :func:`~dic.correlation.points.region` takes -> (JSON form, Region or None)."""
    from ..correlation.points import Region, region

    if value is None:
        return None, None
    if isinstance(value, Region):
        return value.settings(), value
    if shape is not None:
        reg = _checked("roi", region, value, shape)
        return reg.settings(), reg
    if isinstance(value, dict) or (isinstance(value, (list, tuple)) and len(value) == 4
                                   and all(isinstance(c, (int, float)) for c in value)):
        return (value if isinstance(value, dict) else [float(c) for c in value]), None  # a stored form
    raise OptionError("roi", f"roi needs the reference image's shape to be checked, got {value!r}")


def _roi_key(stored):
    """What identifies a region (a mask by its content, not by the file it was read from)."""
    if isinstance(stored, dict) and "mask" in stored:
        return {k: v for k, v in stored.items() if k != "mask"}
    return stored


def _shown(value) -> str:
    if value is None:
        return "none"
    if isinstance(value, dict) and "sha256" in value and "shape" in value and len(value) == 2:
        return f"{value['shape'][0]} points ({value['sha256'][:12]}...)"
    return repr(value) if isinstance(value, str) else str(value)


#: the command-line options that ``specula track`` and ``specula stereo`` share, by record keyword
_SHARED_CLI_NAMES = {
    "subset": "--subset", "step": "--step", "order": "--order", "roi": "--roi/--roi-polygon/--mask/--exclude",
    "noise_sigma": "--noise-sigma", "robust": "--robust/--robust-mode", "strain_window": "--strain-window",
    "reference": "--reference", "guess": "--scheduler/--workers", "subset_mask": "--subset-mask",
    "min_kept_fraction": "--min-kept-fraction", "strain_type": "--strain-type"}


class _Record:
    """What :class:`TrackOptions` and :class:`StereoOptions` share: storage, comparison, messages."""

    #: option keyword -> its command-line option (where the command has one)
    CLI_NAMES: ClassVar[dict[str, str]] = {}
    KIND: ClassVar[str] = ""
    #: options added to the record after its schema-2 form first shipped (b36e3a0) -> the value that
    #: reproduces what a file written without them holds (the behaviour before the option existed).
    #: A schema-2 file that lacks such an option reads as that value, so it still resumes; add a new
    #: option here whenever its default differs from the old behaviour or could change later.
    ADDED_OPTIONS: ClassVar[dict[str, Any]] = {}

    # -- built from a call's keywords
    @classmethod
    def from_keywords(cls, keywords: dict, *, shape=None):
        """The record of a sequence call's keywords (:func:`dic.sequence.track_sequence`'s or
        :func:`dic.sequence.stereo_sequence`'s ``options`` and the sequence's own). ``shape`` (H, W) px: the
        (left) reference image's, to check a ``roi`` given in any form. Unknown keywords raise
        :class:`OptionError`; ``device`` is not an option of the record."""
        kw = {k: v for k, v in keywords.items() if k != "device"}
        names = {f.name for f in fields(cls) if f.compare}
        unknown = sorted(set(kw) - names)
        if unknown:
            raise OptionError(unknown[0], f"unknown option(s) {', '.join(unknown)}; the options are "
                                          f"{', '.join(sorted(names))} (and device)")
        if kw.get("roi") is not None:
            kw["roi"] = _roi(kw["roi"], shape)[1] or kw["roi"]
        return cls(**kw)

    def _require_inputs(self, what: str) -> None:
        """A record read from a file holds digests of its POIs and region, not them: refused to ``what``."""
        if (self.points is not None and self.points_array is None) or (self.roi is not None and self.region is None):
            raise ValueError("a run record read from a file holds only digests of its POIs and region; "
                             f"build the record from the options to {what}")

    # -- the stored form
    def to_settings(self) -> dict:
        """The settings stored in a result file: every option (defaults included) and ``options_schema``."""
        out = {f.name: getattr(self, f.name) for f in fields(self) if f.compare}
        out[_SCHEMA_KEY] = OPTIONS_SCHEMA
        return out

    @classmethod
    def from_settings(cls, settings: dict):
        """The record a file's settings describe (any schema). Options a schema-1 file did not record
        (its writer did not compare them either) are listed in :attr:`unrecorded` and match any value."""
        if not isinstance(settings, dict):
            raise ValueError(f"settings must be a dict, got {type(settings).__name__}")
        version = settings.get(_SCHEMA_KEY, 1)
        if version == OPTIONS_SCHEMA:
            names = {f.name for f in fields(cls) if f.compare}
            unknown = sorted(set(settings) - names - {_SCHEMA_KEY})
            added = {k: v for k, v in cls.ADDED_OPTIONS.items() if k not in settings}
            settings = {**settings, **added}
            missing = sorted(names - set(settings))
            if unknown or missing:
                raise ValueError(f"settings of schema {OPTIONS_SCHEMA} with unknown options {unknown} or without "
                                 f"{missing}: not a {cls.KIND} run record")
            kw = {k: v for k, v in settings.items() if k != _SCHEMA_KEY}
            return cls(**kw)
        if version != 1:
            raise ValueError(f"settings of options schema {version!r}: this Specula reads schemas 1 and {OPTIONS_SCHEMA}")
        record = cls._from_schema1(settings)
        added = {k: v for k, v in cls.ADDED_OPTIONS.items() if k not in settings}  # older still: the old behaviour
        return replace(record, **added) if added else record

    def differences(self, other) -> list[tuple[str, Any, Any]]:
        """``(option, value here, value in other)`` for every option that differs (those either side did
        not record excluded)."""
        skip = self.unrecorded | other.unrecorded
        out = []
        for f in fields(self):
            if not f.compare or f.name in skip or self._inert(other, f.name):
                continue
            a, b = getattr(self, f.name), getattr(other, f.name)
            if f.name == "roi":
                a, b = _roi_key(a), _roi_key(b)
            if a != b:
                out.append((f.name, getattr(self, f.name), getattr(other, f.name)))
        return out

    def resume_check(self, stored_settings: dict) -> str | None:
        """None when a file whose settings are ``stored_settings`` holds the results of this run (any
        schema, any writer); else what differs, for the refusal (used by :class:`dic.store.ResultWriter`)."""
        try:
            stored = type(self).from_settings(stored_settings)
        except ValueError as exc:
            return (f"its settings are not those of a {self.KIND} run ({exc}); start afresh with --overwrite "
                    "(mode='overwrite' in Python) or write to another file")
        diff = stored.differences(self)
        if not diff:
            return None
        parts = []
        for name, old, new in diff:
            cli = self.CLI_NAMES.get(name)
            label = f"{cli} ({name})" if cli else name
            parts.append(f"{label}: {_shown(old)} in the file, {_shown(new)} now")
        return ("; ".join(parts) + ". Resume with the file's settings, or start afresh with --overwrite "
                "(mode='overwrite' in Python) or write to another file")

    # -- the sequence-level options shared by both kinds
    def _check_sequence(self) -> None:
        policy = _checked("reference", parse_reference, self.reference,
                          auto_valid=AUTO_VALID if self.auto_valid is None else self.auto_valid,
                          auto_zncc=AUTO_ZNCC if self.auto_zncc is None else self.auto_zncc)
        self._set("reference", policy.text)
        auto = policy.kind == "auto"
        self._set("auto_valid", policy.auto_valid if auto else None)
        self._set("auto_zncc", policy.auto_zncc if auto else None)
        if self.guess not in ("previous", "none"):
            raise OptionError("guess", f"guess must be 'previous' or 'none', got {self.guess!r}")

    def _set(self, name: str, value) -> None:
        object.__setattr__(self, name, value)

    def _subset_mask_options(self) -> None:
        """``subset_mask`` and ``min_kept_fraction`` checked (written as given; :meth:`_inert` says when they
        cannot act)."""
        self._set("subset_mask", _checked("subset_mask", check_subset_mask, self.subset_mask))
        self._set("min_kept_fraction", _checked("min_kept_fraction", check_min_kept_fraction, self.min_kept_fraction))

    def _subset_mask_kwargs(self) -> dict:
        """The tracker keywords of the two options."""
        return {"subset_mask": self.subset_mask, "min_kept_fraction": self.min_kept_fraction}

    def _inert(self, other, name: str) -> bool:
        """Whether option ``name`` cannot change the results of either record, so that a difference in it is
        none: ``subset_mask`` without a mask or polygon ROI on either side (no ROI or a box: nothing is
        masked), ``min_kept_fraction`` unless a side masks its subsets. A file written before the options
        (read as "none", 0.5) thus resumes with today's defaults unless its run had a mask or polygon ROI."""
        if name not in ("subset_mask", "min_kept_fraction"):
            return False
        masks = [isinstance(r.roi, dict) and r.subset_mask == "region" for r in (self, other)]  # dict: mask, polygon
        if name == "subset_mask":
            return not (isinstance(self.roi, dict) or isinstance(other.roi, dict))
        return not any(masks)

    def _check_common(self) -> None:
        self._set("subset", _checked("subset", odd_int, self.subset, "subset", detail=" (e.g. 21)"))
        if isinstance(self.order, bool) or self.order not in (1, 2):
            raise OptionError("order", "order must be 1 (affine, 6 parameters) or 2 (quadratic, 12 parameters), "
                                       f"got {self.order!r}")
        self._set("order", int(self.order))
        self._set("max_iter", _checked("max_iter", positive_int, self.max_iter, "max_iter", maximum=_MAX_ITER,
                                       detail=" (IC-GN iterations per point)"))
        self._set("tol", _checked("tol", positive_float, self.tol, "tol", detail=" of pixels"))
        self._set("zncc_min", _checked("zncc_min", in_range, self.zncc_min, -1.0, 1.0, "zncc_min"))
        self._set("check_warps", _checked("check_warps", boolean, self.check_warps, "check_warps"))
        if self.noise_sigma is not None:
            self._set("noise_sigma", _checked("noise_sigma", positive_float, self.noise_sigma, "noise_sigma",
                                              detail=" (grey levels)"))
        from ..correlation.engine import check_robust

        self._set("robust", _checked("robust", check_robust, self.robust))
        digest, arr = _points(self.points)
        self._set("points", digest)
        if arr is not None:
            self._set("points_array", arr)
        if self.roi is not None and self.points is not None:
            raise OptionError("roi", "give either points or roi (roi selects grid points), not both")


def _schema1_subset_mask(kw: dict) -> None:
    """A schema-1 run with a mask or polygon ROI correlated every subset pixel: ``subset_mask`` "none" (issue 26;
    elsewhere the option cannot act and keeps its default)."""
    if isinstance(kw.get("roi"), dict):
        kw.setdefault("subset_mask", "none")


def _schema1_sequence(settings: dict) -> dict:
    """The sequence-level options of schema-1 settings (written only when not the default)."""
    kw = {"reference": settings.get("reference", "fixed"), "guess": settings.get("guess", "previous")}
    for k in ("auto_valid", "auto_zncc"):
        if k in settings:
            kw[k] = settings[k]
    return kw


@dataclass(frozen=True)
class TrackOptions(_Record):
    """Every option of a 2-D sequence (:func:`dic.sequence.track_sequence`) that affects its results.

    The :class:`dic.Tracker` options (``subset`` px, ``step`` px, ``order``, ``points`` (N, 2) px,
    ``roi``, ``search`` and ``search_radius`` px, ``max_iter``, ``tol`` px, ``zncc_min``, ``flat_std``
    grey levels, ``check_warps``, ``noise_sigma`` grey levels, ``robust``, ``check_outliers``) and the
    sequence's (``strain_window`` grid points, ``reference``, ``auto_valid``, ``auto_zncc``, ``guess``,
    ``scale_mm_per_px``, recorded for post-processing), ``cracks``: declared cracks (:mod:`dic.cracks`),
    stored as a list of vertex lists ``[[x, y], ...]`` px, None without any, and ``verify_composed`` and
    ``verify_zncc``, the check of composed results against the reference image
    (:mod:`dic.sequence.verification`). The device is not one: it does not change the results a file
    holds beyond rounding.
    """

    subset: int = 21
    step: int | None = None
    order: int = 1
    points: Any = None
    roi: Any = None
    search: str | None = None
    search_radius: int | None = 32
    max_iter: int = 30
    tol: float = 1e-3
    zncc_min: float = 0.8
    flat_std: float | None = None
    check_warps: bool = True
    noise_sigma: float | None = None
    robust: bool | str = "adaptive"
    check_outliers: bool | None = None
    strain_window: int = 5
    reference: str = "fixed"
    auto_valid: float | None = None
    auto_zncc: float | None = None
    guess: str = "previous"
    scale_mm_per_px: float | None = None
    # -- per-POI pixel masks (issue 26: holes, free edges; dic.correlation.subset_masks)
    subset_mask: str = "region"
    min_kept_fraction: float = 0.5
    # -- crack26: declared cracks (dic.cracks), stored as a list of vertex lists [[x, y], ...] px; None: no cracks
    cracks: Any = None
    # -- re-verification of composed results (dic.sequence.verification; issue 26)
    verify_composed: bool | None = True
    verify_zncc: float | None = None
    # strain types by name (issue 25): what exx, eyy, exy are; files before it computed small strain
    strain_type: str = "green-lagrange"
    # -- verifyrel: the composed check's threshold lowered to each frame's median ZNCC less verify_spread robust
    # standard deviations (kernels.verify.composed_threshold); "off": verify_zncc alone, the rule before it
    verify_spread: float | str | None = None
    #: the POIs given (None when read from a file: it holds their digest only)
    points_array: Any = field(default=None, compare=False, repr=False)
    #: the checked region (None when read from a file: it holds its JSON form)
    region: Any = field(default=None, compare=False, repr=False)
    #: options a schema-1 file did not record (they match any value)
    unrecorded: frozenset = field(default=frozenset(), compare=False, repr=False)

    CLI_NAMES: ClassVar[dict[str, str]] = {
        **_SHARED_CLI_NAMES, "search": "--search-method", "search_radius": "--search", "max_iter": "--max-iter",
        "tol": "--tol", "scale_mm_per_px": "--scale", "cracks": "--crack", "verify_composed": "--verify-composed",
        "verify_zncc": "--verify-zncc", "verify_spread": "--verify-spread"}
    KIND: ClassVar[str] = "2-D"
    # (strain_type: 2-D exx was the small strain before the option)
    ADDED_OPTIONS: ClassVar[dict[str, Any]] = {"subset_mask": "none", "min_kept_fraction": 0.5, "cracks": None,
                                               "verify_composed": False, "verify_zncc": None, "strain_type": "small",
                                               "verify_spread": "off"}
    #: the keywords of :func:`dic.sequence.track_sequence` itself (not the tracker's)
    SEQUENCE_KEYWORDS: ClassVar[tuple[str, ...]] = ("strain_window", "reference", "auto_valid", "auto_zncc", "guess",
                                                    "verify_composed", "verify_zncc", "strain_type", "verify_spread")

    def __post_init__(self):
        self._check_common()
        if self.roi is not None:
            json_form, reg = _roi(self.roi, None)
            self._set("roi", json_form)
            if reg is not None:
                self._set("region", reg)
        if self.points is None:
            step = max(1, self.subset // 2) if self.step is None else self.step
            self._set("step", _checked("step", positive_int, step, "step", detail=" number of pixels"))
        elif self.step is not None:
            self._set("step", _checked("step", positive_int, self.step, "step", detail=" number of pixels"))
        if self.search is not None:
            self._set("search", _checked("search", _check_search, self.search))
            self._set("search_radius", _checked("search_radius", non_negative_int, self.search_radius,
                                                "search_radius", detail=" (px)"))
        else:
            if self.search_radius is not None:
                _checked("search_radius", non_negative_int, self.search_radius, "search_radius", detail=" (px)")
            self._set("search_radius", None)
        if self.flat_std is not None:
            v = _checked("flat_std", in_range, self.flat_std, 0.0, math.inf, "flat_std", detail=" (grey levels)")
            if not math.isfinite(v):
                raise OptionError("flat_std", f"flat_std must be a finite non-negative grey level, got {self.flat_std!r}")
            self._set("flat_std", v)
        outliers = bool(self.robust) if self.check_outliers is None else self.check_outliers
        self._set("check_outliers", _checked("check_outliers", boolean, outliers, "check_outliers"))
        sw = _checked("strain_window", non_negative_int, self.strain_window, "strain_window")
        if sw and (sw < 3 or sw % 2 == 0):
            raise OptionError("strain_window", f"strain_window must be 0 (no strain) or an odd integer >= 3 "
                                               f"(grid points), got {self.strain_window!r}")
        self._set("strain_window", sw)
        self._set("strain_type", _checked("strain_type", _strain_type, self.strain_type))
        if self.scale_mm_per_px is not None:
            self._set("scale_mm_per_px", _checked("scale_mm_per_px", positive_float, self.scale_mm_per_px,
                                                  "the scale", detail=" (mm per px)"))
        self._subset_mask_options()
        self._set("cracks", _cracks(self.cracks))
        self._check_sequence()
        self._check_verification()

    def _check_verification(self) -> None:
        """``verify_composed`` a bool, None with the fixed reference (nothing is composed: it cannot act); None
        given with a moved reference is the default, on. ``verify_zncc`` in [-1, 1],
        :data:`dic.sequence.verification.VERIFY_ZNCC` (0.95) when not given, and None where the check does not
        run."""
        if self.reference == "fixed":
            self._set("verify_composed", None)
        elif self.verify_composed is None:
            self._set("verify_composed", True)
        else:
            self._set("verify_composed", _checked("verify_composed", boolean, self.verify_composed, "verify_composed"))
        if self.verify_zncc is not None:
            self._set("verify_zncc", _checked("verify_zncc", in_range, self.verify_zncc, -1.0, 1.0, "verify_zncc"))
        if not self.verify_composed:
            self._set("verify_zncc", None)
        elif self.verify_zncc is None:
            self._set("verify_zncc", VERIFY_ZNCC)
        # verify_spread: robust standard deviations (float), "off" (verify_zncc alone), None where the check does
        # not run; VERIFY_SPREAD when not given
        if not self.verify_composed:
            self._set("verify_spread", None)
        elif self.verify_spread is None:
            self._set("verify_spread", VERIFY_SPREAD)
        else:
            spread = _checked("verify_spread", check_verify_spread, self.verify_spread)
            self._set("verify_spread", "off" if spread is None else spread)

    def tracker_kwargs(self) -> dict:
        """The :class:`dic.Tracker` keywords of this record (no ``device``): the POIs as given, the
        checked region (a record read from a file has neither: it cannot build a tracker)."""
        self._require_inputs("track")
        kw = {"subset": self.subset, "step": self.step, "order": self.order, "search": self.search,
              "max_iter": self.max_iter, "tol": self.tol, "zncc_min": self.zncc_min, "flat_std": self.flat_std,
              "check_warps": self.check_warps, "noise_sigma": self.noise_sigma, "robust": self.robust,
              "check_outliers": self.check_outliers, **self._subset_mask_kwargs()}
        if self.search is not None:
            kw["search_radius"] = self.search_radius
        if self.points_array is not None:
            kw["points"] = self.points_array
        if self.region is not None:
            kw["roi"] = self.region
        if self.cracks is not None:
            kw["cracks"] = self.cracks
        return kw

    @classmethod
    def _from_schema1(cls, s: dict) -> "TrackOptions":
        kw = _schema1_sequence(s)
        unrecorded = set()
        if kw["reference"] == "auto" and "auto_valid" not in s:  # 8d9f975 wrote them only with guess="none"
            unrecorded |= {"auto_valid", "auto_zncc"}
        if "search_method" in s:  # the command line's form: search = the radius, search_method = the method
            radius, method = s.get("search"), s.get("search_method")
            kw["search"] = method if radius is not None else None
            if radius is not None:
                kw["search_radius"] = radius
            for k in ("subset", "step", "order", "strain_window", "noise_sigma", "roi", _SCALE_KEY, "strain_type"):
                if s.get(k) is not None:
                    kw[k] = s[k]
            for k in ("max_iter", "tol"):  # null: the tracker's default
                if s.get(k) is not None:
                    kw[k] = s[k]
            kw["robust"] = bool(s.get("robust"))  # absent: off (before the adaptive default)
            known = {"search", "search_method", "subset", "step", "order", "strain_window", "noise_sigma", "roi",
                     _SCALE_KEY, "max_iter", "tol", "robust", "reference", "guess", "auto_valid", "auto_zncc",
                     "strain_type"}  # strain_type: written by specula strain into an old file
        else:  # the library's form: the keywords given (others at their defaults)
            known = {f.name for f in fields(cls) if f.compare}
            kw.update({k: v for k, v in s.items() if k in known and k not in kw})
            kw.setdefault("robust", False)  # absent: the default then, off (before the adaptive default)
        unknown = sorted(set(s) - known)
        if unknown:
            raise ValueError(f"unknown settings {', '.join(unknown)}")
        _schema1_subset_mask(kw)
        return replace(cls(**kw), unrecorded=frozenset(unrecorded))


@dataclass(frozen=True)
class StereoOptions(_Record):
    """Every option of a stereo sequence (:func:`dic.sequence.stereo_sequence`) that affects its results.

    The :class:`dic.StereoCorrelation` options (``subset`` px, ``step`` px (default ``subset // 2``; None with ``points``:
    their spacing), ``order``, ``points`` (N, 2) px in the left image, ``roi``, ``frame`` ("left",
    "plane" or ``[R_obj_left, t_obj_left]``), ``epipolar_tol_px``, ``zncc_min``, ``strain_window``
    grid points, ``max_iter``, ``tol`` px, ``triangulation``, ``max_features``, ``check_warps``,
    ``noise_sigma`` grey levels, ``robust``) and the sequence's (``reference``, ``auto_valid``,
    ``auto_zncc``, ``guess``), and ``verify_composed`` / ``verify_zncc``, the check of composed tracks against
    the reference pair (:mod:`dic.correlation.stereo_verify`; resolved as :class:`TrackOptions` does), and
    ``right_track_mask``, the right temporal track's subsets masked by the left region mapped through the
    match (:mod:`dic.correlation.right_masks`), and ``cracks``, declared cracks in left reference px
    (:mod:`dic.stereo_cracks`; stored as :class:`TrackOptions` stores them), and ``motion_prediction``, the
    temporal tracks' start from the states before ("velocity"; "none", the files written before it; None: not chosen,
    resolved by :func:`dic.sequence.stereo_sequence`: "velocity" for a new file, a resumed file's own). The device
    is not one.
    """

    subset: int = 21
    step: int | None = None
    order: int = 1
    points: Any = None
    roi: Any = None
    frame: Any = "left"
    epipolar_tol_px: float = 1.0
    zncc_min: float = 0.8
    strain_window: int = 5
    max_iter: int = 50
    tol: float = 1e-3
    triangulation: str = "optimal"
    max_features: int = 20000
    check_warps: bool = True
    noise_sigma: float | None = None
    robust: bool | str = False
    reference: str = "fixed"
    auto_valid: float | None = None
    auto_zncc: float | None = None
    guess: str = "previous"
    # -- per-POI pixel masks of the left reference's subsets (issue 26; dic.correlation.subset_masks)
    subset_mask: str = "region"
    min_kept_fraction: float = 0.5
    # strain types by name (issue 25): what exx, eyy, exy are; stereo strain was always Green-Lagrange
    strain_type: str = "green-lagrange"
    # -- stereo26: re-verification of composed tracks against the reference pair (dic.correlation.stereo_verify)
    verify_composed: bool | None = True
    verify_zncc: float | None = None
    # -- stereo26: the right track's subsets masked by the left region mapped through the match (dic.correlation.right_masks)
    right_track_mask: bool = True
    # -- stereo26: declared cracks in left reference px (dic.stereo_cracks), stored as 2-D's; None: no cracks
    cracks: Any = None
    # -- verifyrel: the composed check's threshold lowered per state and camera (as TrackOptions.verify_spread)
    verify_spread: float | str | None = None
    # -- the temporal tracks' start: "velocity" (the two states before, extrapolated) or "none" (the previous state);
    # None: not chosen, which stereo_sequence resolves (a new file "velocity", a resumed file the value it was written
    # with) before the record is stored
    motion_prediction: str | None = None
    points_array: Any = field(default=None, compare=False, repr=False)
    region: Any = field(default=None, compare=False, repr=False)
    unrecorded: frozenset = field(default=frozenset(), compare=False, repr=False)

    CLI_NAMES: ClassVar[dict[str, str]] = {
        **_SHARED_CLI_NAMES, "frame": "--frame", "epipolar_tol_px": "--epipolar-tol", "zncc_min": "--zncc-min",
        "verify_composed": "--verify-composed", "verify_zncc": "--verify-zncc", "right_track_mask": "--right-track-mask",
        "cracks": "--crack", "verify_spread": "--verify-spread", "motion_prediction": "--motion-prediction"}
    KIND: ClassVar[str] = "stereo"
    ADDED_OPTIONS: ClassVar[dict[str, Any]] = {"subset_mask": "none", "min_kept_fraction": 0.5,
                                               "strain_type": "green-lagrange",
                                               "verify_composed": False, "verify_zncc": None,
                                               "right_track_mask": False, "cracks": None, "verify_spread": "off",
                                               "motion_prediction": "none"}
    SEQUENCE_KEYWORDS: ClassVar[tuple[str, ...]] = ("reference", "auto_valid", "auto_zncc", "guess",
                                                    "verify_composed")
    # verify_composed / verify_zncc resolved as for 2-D runs (None with the fixed reference; 0.95 by default)
    _check_verification = TrackOptions._check_verification

    def _inert(self, other, name: str) -> bool:
        """As :meth:`_Record._inert`, and ``right_track_mask`` cannot act unless a side masks its subsets (a mask
        or polygon ROI with ``subset_mask="region"``): a file written before it resumes unless its run had one."""
        if name == "right_track_mask":
            return not any(isinstance(r.roi, dict) and r.subset_mask == "region" for r in (self, other))
        if name == "motion_prediction":  # not chosen on one side: that side takes the other's (a resumed file's)
            return self.motion_prediction is None or other.motion_prediction is None
        return super()._inert(other, name)

    def __post_init__(self):
        self._check_common()
        if self.roi is not None:
            json_form, reg = _roi(self.roi, None)
            self._set("roi", json_form)
            if reg is not None:
                self._set("region", reg)
        if self.points is None:  # default: subset // 2, the 2-D rule
            step = max(1, self.subset // 2) if self.step is None else self.step
            self._set("step", _checked("step", positive_int, step, "step", detail=" number of pixels"))
        else:
            self._set("step", None)  # the POIs' spacing
        self._set("frame", _frame(self.frame))
        self._set("epipolar_tol_px", _checked("epipolar_tol_px", positive_float, self.epipolar_tol_px,
                                              "epipolar_tol_px"))
        self._set("strain_window", _checked("strain_window", odd_int, self.strain_window, "strain window",
                                            detail=" (grid points)", integral_float=True))
        if self.triangulation not in ("optimal", "linear"):
            raise OptionError("triangulation", f"triangulation must be 'optimal' or 'linear', got {self.triangulation!r}")
        self._set("max_features", _checked("max_features", positive_int, self.max_features, "max_features"))
        self._subset_mask_options()
        self._set("strain_type", _checked("strain_type", _strain_type, self.strain_type))
        self._check_sequence()
        self._check_verification()
        self._set("right_track_mask", _checked("right_track_mask", boolean, self.right_track_mask, "right_track_mask"))
        self._set("cracks", _cracks(self.cracks))
        from .._stereo import MOTION_PREDICTIONS

        if self.motion_prediction is not None and self.motion_prediction not in MOTION_PREDICTIONS:
            raise OptionError("motion_prediction", f"motion_prediction must be one of {', '.join(MOTION_PREDICTIONS)}, "
                                                   f"got {self.motion_prediction!r}")

    def correlation_kwargs(self) -> dict:
        """The :class:`dic.StereoCorrelation` keywords of this record (no ``device``, no ``match``)."""
        self._require_inputs("measure")
        frame = self.frame if isinstance(self.frame, str) else (np.asarray(self.frame[0]), np.asarray(self.frame[1]))
        kw = {"subset": self.subset, "order": self.order, "frame": frame, "epipolar_tol_px": self.epipolar_tol_px,
              "zncc_min": self.zncc_min, "strain_window": self.strain_window, "max_iter": self.max_iter,
              "tol": self.tol, "triangulation": self.triangulation, "max_features": self.max_features,
              "check_warps": self.check_warps, "noise_sigma": self.noise_sigma, "robust": self.robust,
              **self._subset_mask_kwargs(), "strain_type": self.strain_type,
              "verify_zncc": self.verify_zncc if self.verify_composed else None,
              "verify_spread": self.verify_spread if self.verify_composed else None,
              "right_track_mask": self.right_track_mask, "cracks": self.cracks}
        if self.motion_prediction is not None:  # None: StereoCorrelation's default, or the resumed file's
            kw["motion_prediction"] = self.motion_prediction
        if self.points_array is not None:
            kw["points"] = self.points_array
        else:
            kw["step"] = self.step
        if self.region is not None:
            kw["roi"] = self.region
        return kw

    @classmethod
    def _from_schema1(cls, s: dict) -> "StereoOptions":
        # one form (the command line passed its options as keywords): the keywords given, others at their defaults
        kw = _schema1_sequence(s)
        known = {f.name for f in fields(cls) if f.compare}
        unknown = sorted(set(s) - known)
        if unknown:
            raise ValueError(f"unknown settings {', '.join(unknown)}")
        kw.update({k: v for k, v in s.items() if k not in kw})
        # 8d9f975 correlated with 2nd order unless told otherwise (the default is 1st order since issue 25)
        kw.setdefault("order", 2)
        kw.setdefault("robust", False)  # absent: the default then, off (before the adaptive default)
        if isinstance(kw.get("points"), list):  # schema 1 stored the coordinates themselves
            kw["points"] = _points_digest(kw["points"])
        _schema1_subset_mask(kw)
        return cls(**kw)


def _cracks(value):
    """Declared cracks (any form :func:`dic.cracks.as_cracks` takes) -> their stored form (None: no cracks)."""
    from ..cracks import cracks_settings

    try:
        return cracks_settings(value)
    except ValueError as exc:
        raise OptionError("cracks", f"cracks: {exc}") from None


def _frame(frame):
    """The output frame as stored: "left", "plane" or ``[R_obj_left (3x3 list), t_obj_left (3 list)]``."""
    if isinstance(frame, str):
        if frame not in ("left", "plane"):
            raise OptionError("frame", f"frame must be 'left', 'plane' or (R_obj_left, t_obj_left), got {frame!r}")
        return frame
    from ..field3d import as_frame

    R, t = _checked("frame", as_frame, frame)
    return [R.tolist(), t.tolist()]


def _strain_type(strain_type):
    from .._strain import check_strain_type

    return check_strain_type(strain_type)


def _check_search(search):
    from ..correlation.guesses import TRACKING_SEARCHES, available_guesses

    names = tuple(n for n in available_guesses() if n != "epipolar")
    if not isinstance(search, str) or search not in names:
        raise ValueError(f"search must be None or one of {TRACKING_SEARCHES} (also accepted: "
                         f"{', '.join(n for n in names if n not in TRACKING_SEARCHES)}), got {search!r}")
    return search

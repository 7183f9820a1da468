"""The public surface of dic (issue 23, item 5): each public name is one thing, and track() takes every
Tracker option."""
import inspect
from pathlib import Path

import dic


def test_every_public_name_resolves_and_functions_stay_functions():
    for name in dic.__all__:
        assert getattr(dic, name) is not None, name
    for name in ("track", "strain", "stereo", "triangulate"):
        assert inspect.isfunction(getattr(dic, name)), name
    # the classes the docs name next to them
    assert inspect.isclass(dic.StrainPlan) and inspect.isclass(dic.Tracker) and inspect.isclass(dic.StereoCorrelation)
    # the implementation modules are private: no public module of the same name shadows a function
    package = Path(dic.__file__).parent
    for name in ("track", "strain", "stereo", "triangulate"):
        assert not (package / f"{name}.py").exists() and (package / f"_{name}.py").exists(), name


def test_every_export_has_one_naming_scheme():
    for fmt in ("csv", "mat", "netcdf", "vtk", "vtk_series", "pvd"):
        assert callable(getattr(dic, f"write_{fmt}"))
    assert callable(dic.export_results) and callable(dic.to_dataframe) and callable(dic.to_xarray)


def test_track_takes_every_tracker_option():
    tracker = set(inspect.signature(dic.Tracker.__init__).parameters) - {"self", "reference"}
    track = set(inspect.signature(dic.track).parameters) - {"reference", "current", "guess"}
    assert tracker == track, (tracker ^ track)


def test_track_passes_robust_and_check_outliers_through():
    ref, cur = dic.synth.speckle_pair((96, 96), displacement=(0.3, 0.0), seed=3)
    plain = dic.track(ref, cur, step=16, subset=21)
    robust = dic.track(ref, cur, step=16, subset=21, robust=True, check_outliers=False)
    assert robust.valid.any() and plain.valid.any()
    tr = dic.Tracker(ref, step=16, subset=21, robust=True, check_outliers=False)
    same = tr.track(cur)
    assert (same.u == robust.u).all() and (same.v == robust.v).all()

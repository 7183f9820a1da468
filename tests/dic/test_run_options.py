"""The run record (dic.sequence.options): one settings record for the library and the command line.

A result file written by ``track_sequence``/``stereo_sequence`` resumes with ``specula track``/``specula
stereo`` and the other way round; a default written out is the default; files written by Specula
8d9f975 (tests/data/settings_v1, made by its make_files.py from the PNGs there: both settings forms
of 2-D, stereo from the library and the command line) still resume; a real difference is refused
with the options named.

Images: tests/data/settings_v1 (2-D: 100 x 80 px speckle, frames shifted by (0.6, -0.3) px per
frame; stereo: the virtual lab of tests/dic/test_stereo_dic.py at 128 x 96 px, 24 points at step 20).
"""
import shutil
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from dic.cli import main
from dic.sequence import stereo_sequence, track_sequence
from dic.sequence.options import OPTIONS_SCHEMA, OptionError, StereoOptions, TrackOptions
from dic.store import read_results, read_stereo

DATA = Path(__file__).parents[1] / "data" / "settings_v1"
IMG = {k: str(DATA / f"{k}.png") for k in ("ref", "f1", "f2", "L0", "R0", "L1", "R1", "L2", "R2")}
RIG = str(DATA / "rig.json")
ROI = (8, 8, 90, 70)
#: the options of the 2-D files (library keywords; the command line's equivalents in CLI_2D)
LIB_2D = dict(step=8, search="zncc", search_radius=4, roi=ROI)
CLI_2D = ["--step", "8", "--search", "4", "--search-method", "zncc", "--roi", *map(str, ROI)]


def _cli(*args):
    return CliRunner().invoke(main, [*args, "--device", "cpu", "-q"])


def _copy(name, tmp_path) -> Path:
    out = tmp_path / name
    shutil.copy(DATA / name, out)
    return out


def _track_cli(out, frames, *extra):
    return _cli("track", IMG["ref"], *[IMG[f] for f in frames], "-o", str(out), *CLI_2D, *extra)


def _track_lib(out, frames, **kw):
    return track_sequence(IMG["ref"], [IMG[f] for f in frames], out, device="cpu", **{**LIB_2D, **kw})


def _pairs(n):
    return [(IMG[f"L{k}"], IMG[f"R{k}"]) for k in range(n)]


def _stereo_cli(out, n, *extra):
    return _cli("stereo", "--rig", RIG, *[p for pair in _pairs(n) for p in pair], "-o", str(out), "--step", "20",
                *extra)


# -- the record ----------------------------------------------------------------------------------
def test_every_default_is_written_and_an_explicit_default_is_the_default():
    rec = TrackOptions()
    settings = rec.to_settings()
    assert settings["options_schema"] == OPTIONS_SCHEMA == 2
    # every option, with the values dic.Tracker and track_sequence use by default
    assert settings == {"options_schema": 2, "subset": 21, "step": 10, "order": 1, "points": None, "roi": None,
                        "search": None, "search_radius": None, "max_iter": 30, "tol": 1e-3, "zncc_min": 0.8,
                        "flat_std": None, "check_warps": True, "noise_sigma": None, "robust": "adaptive",
                        "check_outliers": True, "strain_window": 5, "reference": "fixed", "auto_valid": None,
                        "auto_zncc": None, "guess": "previous", "scale_mm_per_px": None, "subset_mask": "region",
                        "min_kept_fraction": 0.5, "cracks": None, "verify_composed": None, "verify_zncc": None,
                        "strain_type": "green-lagrange", "verify_spread": None}
    from dic.postprocess import SCALE_KEY

    assert SCALE_KEY in settings  # where post-processing reads the scale
    explicit = TrackOptions(subset=21, step=10, max_iter=30, tol=0.001, check_outliers=True, robust="adaptive")
    assert explicit == rec and not rec.differences(explicit)
    assert TrackOptions.from_settings(settings) == rec
    # derived defaults: robust IC-GN (on or adaptive) checks outliers; auto thresholds only with reference="auto"
    assert TrackOptions(robust=True).check_outliers is True and TrackOptions(robust=False).check_outliers is False
    auto = TrackOptions(reference="auto")
    assert (auto.auto_valid, auto.auto_zncc) == (0.95, 0.95) and TrackOptions(reference="auto", auto_valid=0.95) == auto
    stereo = StereoOptions()
    assert stereo.to_settings()["max_iter"] == 50 and stereo.to_settings()["order"] == 1
    assert StereoOptions.from_settings(stereo.to_settings()) == stereo == StereoOptions(step=10, tol=1e-3)


def test_points_and_regions_are_stored_as_their_digest_and_json_form():
    pts = np.array([[20.0, 20.0], [30.0, 25.0], [40.0, 30.0]])
    rec = TrackOptions(points=pts)
    s = rec.to_settings()
    assert s["points"]["shape"] == [3, 2] and len(s["points"]["sha256"]) == 64 and s["step"] is None
    assert np.array_equal(rec.tracker_kwargs()["points"], pts)
    back = TrackOptions.from_settings(s)
    assert back == rec and not back.differences(TrackOptions(points=pts + 0.0))
    assert back.differences(TrackOptions(points=pts + 0.5))[0][0] == "points"
    with pytest.raises(ValueError, match="digests"):  # a record read back cannot build a tracker
        back.tracker_kwargs()
    box = TrackOptions.from_keywords({"roi": ROI}, shape=(80, 100))
    assert box.to_settings()["roi"] == [8.0, 8.0, 90.0, 70.0] and box.tracker_kwargs()["roi"].kind == "box"


@pytest.mark.parametrize("kind, kw, option, fragment", [
    (TrackOptions, {"max_iter": 0}, "max_iter", "max_iter must be an integer in [1, 10000]"),
    (TrackOptions, {"tol": -1.0}, "tol", "tol must be a positive finite number"),
    (TrackOptions, {"subset": 20}, "subset", "subset must be an odd integer"),
    (TrackOptions, {"search": "magic"}, "search", "search must be None or one of"),
    (TrackOptions, {"strain_window": 4}, "strain_window", "strain_window must be 0 (no strain) or an odd"),
    (TrackOptions, {"robust": 1}, "robust", "robust must be True or False"),
    (TrackOptions, {"reference": "every:0"}, "reference", "every:N"),
    (TrackOptions, {"guess": "maybe"}, "guess", "guess must be 'previous' or 'none'"),
    (TrackOptions, {"scale_mm_per_px": 0}, "scale_mm_per_px", "the scale must be a positive finite number"),
    (StereoOptions, {"triangulation": "fast"}, "triangulation", "triangulation must be 'optimal' or 'linear'"),
    (StereoOptions, {"frame": "right"}, "frame", "frame must be 'left', 'plane'"),
    (StereoOptions, {"epipolar_tol_px": 0}, "epipolar_tol_px", "epipolar_tol_px must be a positive"),
])
def test_bad_options_are_refused_naming_the_option(kind, kw, option, fragment):
    with pytest.raises(OptionError) as info:
        kind(**kw)
    assert info.value.option == option and fragment in str(info.value)
    assert isinstance(info.value, ValueError)


def test_unknown_keywords_are_named(tmp_path):
    with pytest.raises(OptionError, match="unknown option.*max_iters"):
        TrackOptions.from_keywords({"max_iters": 30})
    with pytest.raises(ValueError, match="unknown option.*max_iters"):
        track_sequence(IMG["ref"], [IMG["f1"]], tmp_path / "x.h5", max_iters=30)
    assert not (tmp_path / "x.h5").exists()


def test_settings_of_8d9f975_are_read_as_records():
    # the command line's form (search = radius, search_method = method, max_iter/tol null) and the library's
    # (the keywords given) of the same run are the same record
    cli, lib = (read_results(DATA / f"track_{w}_v1.h5").settings for w in ("cli", "lib"))
    assert "search_method" in cli and cli["search"] == 4 and lib["search"] == "zncc"  # what 8d9f975 wrote
    # strain_type: 8d9f975 computed the small strain in 2-D (TrackOptions.ADDED_OPTIONS), Green-Lagrange in stereo
    # (and correlated every subset pixel: subset_mask "none", issue 26; robust: off, the default before adaptive
    # robust IC-GN became the default; 8d9f975 wrote it only when on)
    expected = TrackOptions(step=8, search="zncc", search_radius=4, roi=[8.0, 8.0, 90.0, 70.0], strain_type="small",
                            subset_mask="none", robust=False)
    assert TrackOptions.from_settings(cli) == expected == TrackOptions.from_settings(lib)
    s_cli, s_lib = (read_stereo(DATA / f"stereo_{w}_v1.h5").settings for w in ("cli", "lib"))
    # 8d9f975's stereo default order was 2 (1 since issue 25): a file that did not record it holds order 2
    # (and its subsets kept every pixel: subset_mask "none", issue 26; stereo: plain IC-GN by default still;
    # its composed tracks were not checked: verify_composed False, and its right tracks not masked:
    # right_track_mask False, issue 26; its tracks started from the previous state: motion_prediction "none")
    assert StereoOptions.from_settings(s_cli) == StereoOptions(step=20, order=2, subset_mask="none",
                                                               right_track_mask=False, motion_prediction="none")
    assert StereoOptions.from_settings(s_lib) == StereoOptions(step=20, reference="incremental", order=2,
                                                               subset_mask="none", verify_composed=False,
                                                               right_track_mask=False, motion_prediction="none")


def test_schema1_details_and_unknown_schemas():
    # 8d9f975 wrote auto_valid/auto_zncc of a 2-D run only with guess="none": when absent they are not compared
    old = {"reference": "auto", "strain_window": 5, "step": 8}
    # (nor did it check composed results: verify_composed False, the default with a moved reference since issue 26;
    # robust absent from a schema-1 file: off, the default then)
    assert TrackOptions(step=8, reference="auto", auto_valid=0.9, strain_type="small",
                        verify_composed=False, robust=False).resume_check(old) is None
    assert "--step (step): 8 in the file, 9 now" in TrackOptions(step=9, reference="auto", robust=False).resume_check(old)
    assert ("--robust/--robust-mode (robust): False in the file, 'adaptive' now"
            in TrackOptions(step=8, reference="auto", auto_valid=0.9).resume_check(old))
    # old stereo files hold the POIs themselves; the record holds their digest
    pts = np.array([[30.0, 30.0], [50.0, 30.0], [30.0, 50.0]])
    assert StereoOptions(points=pts, order=2).resume_check({"points": pts.tolist()}) is None
    assert "points" in StereoOptions(points=pts + 1, order=2).resume_check({"points": pts.tolist()})
    # a schema-1 stereo file that did not record the order was correlated with 8d9f975's default, 2
    assert "--order (order): 2 in the file, 1 now" in StereoOptions(points=pts).resume_check({"points": pts.tolist()})
    # a mask is the same region wherever it was read from
    mask = {"mask": "/a/m.png", "sha256": "ab" * 32, "shape": [80, 100]}
    # (a schema-1 file correlated every subset pixel: the same run now is subset_mask="none", issue 26;
    # its exx was the small strain: strain_type="small", issue 25; robust IC-GN was off)
    assert TrackOptions(roi={**mask, "mask": "/b/m.png"}, subset_mask="none", strain_type="small",
                        robust=False).resume_check({"roi": mask, "strain_window": 5}) is None
    for stored, fragment in (({"options_schema": 3}, "schema 3"), ({"subset": 21, "colour": "red"}, "colour"),
                             ({**TrackOptions().to_settings(), "colour": 1}, "colour")):
        refusal = TrackOptions().resume_check(stored)
        assert fragment in refusal and "--overwrite" in refusal


# -- resuming across writers -------------------------------------------------------------------
def test_2d_library_file_resumes_with_the_cli_and_back(tmp_path):
    out = tmp_path / "lib.h5"
    first = _track_lib(out, ["f1"])
    assert [f["index"] for f in first.frames] == [1]
    u1 = read_results(out).frames[1].u.copy()
    # the command line, defaults written out explicitly (--max-iter 30 --tol 0.001 are the library's defaults)
    r = _track_cli(out, ["f1", "f2"], "--max-iter", "30", "--tol", "0.001", "--strain-window", "5")
    assert r.exit_code == 0, r.output
    res = read_results(out)
    assert sorted(res.frames) == [1, 2] and np.array_equal(res.frames[1].u, u1, equal_nan=True)
    assert res.settings == TrackOptions(**LIB_2D).to_settings()
    # a command-line file resumes in Python
    out2 = tmp_path / "cli.h5"
    assert _track_cli(out2, ["f1"]).exit_code == 0
    again = _track_lib(out2, ["f1", "f2"], max_iter=30)
    assert again.skipped == 1 and [f["index"] for f in again.frames] == [2]
    # both writers stored the same record, and computed the same frame 2
    assert read_results(out2).settings == res.settings
    assert np.array_equal(read_results(out2).frames[2].u, res.frames[2].u, equal_nan=True)


def test_a_real_difference_is_refused_naming_the_options(tmp_path):
    out = tmp_path / "lib.h5"
    _track_lib(out, ["f1"])
    r = _track_cli(out, ["f1", "f2"], "--max-iter", "40", "--order", "2")
    assert r.exit_code == 1 and "Traceback" not in r.output
    text = " ".join(r.output.split())
    assert "was written with different settings" in text
    assert "--max-iter (max_iter): 30 in the file, 40 now" in text and "--order (order): 1 in the file, 2 now" in text
    assert "--overwrite" in text
    with pytest.raises(ValueError, match=r"--search \(search_radius\): 4 in the file, 6 now.*mode='overwrite'"):
        _track_lib(out, ["f1", "f2"], search_radius=6)
    # an option without a command-line flag is named by its keyword
    with pytest.raises(ValueError, match=r"zncc_min: 0\.8 in the file, 0\.7 now"):
        _track_lib(out, ["f1", "f2"], zncc_min=0.7)
    assert sorted(read_results(out).frames) == [1]  # nothing was written by the refused runs


@pytest.mark.parametrize("written_by", ["cli", "lib"])
def test_2d_files_of_8d9f975_resume_with_either_writer(written_by, tmp_path):
    for resume_with in ("cli", "lib"):
        d = tmp_path / resume_with
        d.mkdir()
        out = _copy(f"track_{written_by}_v1.h5", d)
        stored = read_results(out)
        u1, settings = stored.frames[1].u.copy(), dict(stored.settings)
        # its frames hold the small strain (what 2-D computed then): resumed with that type, not today's default
        # Green-Lagrange, which would make exx mean two things in one file (refused, naming the option); robust
        # IC-GN was off by default then (adaptive now): the file's value is given to resume it
        if resume_with == "cli":
            r = _track_cli(out, ["f1", "f2"], "--robust-mode", "off")
            assert r.exit_code == 1 and "--strain-type (strain_type): 'small' in the file, 'green-lagrange' now" in \
                " ".join(r.output.split())
            r = _track_cli(out, ["f1", "f2"], "--strain-type", "small", "--robust-mode", "off")
            assert r.exit_code == 0, r.output
        else:
            s = _track_lib(out, ["f1", "f2"], strain_type="small", robust=False)
            assert s.skipped == 1 and [f["index"] for f in s.frames] == [2]
        res = read_results(out)
        assert sorted(res.frames) == [1, 2] and np.array_equal(res.frames[1].u, u1, equal_nan=True)
        assert res.settings == settings  # the file keeps the settings it was written with
        # frame 2 moved by (1.2, -0.6) px: a resumed run that tracks it is a working run
        f = res.frames[2]
        assert f.valid.sum() >= 0.8 * len(f.valid)
        assert np.max(np.abs(f.u[f.valid] - 1.2)) < 0.05 and np.max(np.abs(f.v[f.valid] + 0.6)) < 0.05
    # a real difference in an old file is refused as well
    with pytest.raises(ValueError, match=r"--step \(step\): 8 in the file, 10 now"):
        _track_lib(out, ["f1", "f2"], step=10, strain_type="small", robust=False)


@pytest.mark.parametrize("written_by", ["cli", "lib"])
def test_stereo_files_of_8d9f975_resume_with_either_writer(written_by, tmp_path):
    # both were written with 8d9f975's default order 2 (the default is 1 since issue 25): resumed with it given
    # (an incremental file of 8d9f975 did not check composed tracks: it resumes with the check off, ADDED_OPTIONS)
    extra = ["--order", "2"] + (["--reference", "incremental", "--no-verify-composed"] if written_by == "lib" else [])
    for resume_with in ("cli", "lib"):
        d = tmp_path / resume_with
        d.mkdir()
        out = _copy(f"stereo_{written_by}_v1.h5", d)
        before = read_stereo(out)
        x1, settings = before.fields[1].xyz.copy(), dict(before.settings)
        if resume_with == "cli":
            r = _stereo_cli(out, 3, *extra)
            assert r.exit_code == 0, r.output
        else:
            fields = stereo_sequence(RIG, _pairs(3), out, step=20, device="cpu", order=2,
                                     reference="incremental" if written_by == "lib" else "fixed",
                                     verify_composed=False if written_by == "lib" else None)
            assert list(fields.indices) == [2]  # a SequenceSummary (the engine)
        res = read_stereo(out)
        assert res.indices == [0, 1, 2] and np.array_equal(res.fields[1].xyz, x1, equal_nan=True)
        assert res.settings == settings
        assert np.count_nonzero(res.fields[2].valid) >= 0.5 * len(res.fields[2])
    with pytest.raises(ValueError, match=r"--zncc-min \(zncc_min\): 0\.8 in the file, 0\.9 now"):
        stereo_sequence(RIG, _pairs(3), out, step=20, zncc_min=0.9, device="cpu", order=2,
                        reference="incremental" if written_by == "lib" else "fixed",
                        verify_composed=False if written_by == "lib" else None)


def test_stereo_library_file_resumes_with_the_cli_and_a_difference_is_refused(tmp_path):
    out = tmp_path / "s.h5"
    stereo_sequence(RIG, _pairs(2), out, step=20, device="cpu", max_iter=50, order=1)  # explicit defaults
    # a new file records the motion prediction it was written with (not chosen: "velocity")
    assert read_stereo(out).settings == StereoOptions(step=20, motion_prediction="velocity").to_settings()
    r = _stereo_cli(out, 3)
    assert r.exit_code == 0, r.output
    assert read_stereo(out).indices == [0, 1, 2]
    r = _stereo_cli(tmp_path / "s.h5", 3, "--frame", "plane", "--overwrite")  # overwrite: allowed
    assert r.exit_code == 0, r.output
    r = _stereo_cli(tmp_path / "s.h5", 3, "--epipolar-tol", "2")
    text = " ".join(r.output.split())
    assert r.exit_code == 1 and "--epipolar-tol (epipolar_tol_px): 1.0 in the file, 2.0 now" in text
    assert "--frame (frame): 'plane' in the file, 'left' now" in text  # every difference, not just the first


def test_result_writer_compares_settings_with_the_check_it_is_given(tmp_path):
    from dic.store import ResultWriter

    out = tmp_path / "w.h5"
    kw = dict(reference_path="r.tif", reference_shape=(10, 10), reference_sha256="abc")
    old = {"search": 4, "search_method": "zncc", "max_iter": None, "tol": None, "subset": 21, "step": 8, "order": 1,
           "strain_window": 5}  # the 8d9f975 command line's form
    with ResultWriter(out, settings=old, **kw):
        pass
    now = TrackOptions(step=8, search="zncc", search_radius=4, max_iter=30, strain_type="small",
                       robust=False)  # 8d9f975: small strain, robust off
    # equal records: resumed, and the file keeps the settings it holds
    with ResultWriter(out, settings=now.to_settings(), settings_check=now.resume_check, **kw):
        pass
    assert read_results(out).settings == old
    # without the check the JSON texts are compared, as for settings given as a dict
    with pytest.raises(ValueError, match=r"different settings \(.*differ"):
        ResultWriter(out, settings=now.to_settings(), **kw)
    other = TrackOptions(step=8, search="zncc", search_radius=4, max_iter=31, strain_type="small", robust=False)
    with pytest.raises(ValueError, match=r"w\.h5 was written with different settings: --max-iter \(max_iter\): 30 in "
                                         r"the file, 31 now\. Resume with the file's settings, or start afresh"):
        ResultWriter(out, settings=other.to_settings(), settings_check=other.resume_check, **kw)


def test_stereo_noise_sigma_from_the_command_line_is_used_recorded_and_compared(tmp_path):
    """``specula stereo --noise-sigma`` (issue 25 item 4): the given noise is behind every stage's sigma, it is
    stored in the run record, a resume with another value is refused naming the option, and a file written
    before the option existed (no ``noise_sigma`` in its settings) resumes without it and is refused with it."""
    import pandas as pd

    from dic.tabular import SIGMA_3D

    out = tmp_path / "n.h5"
    r = _stereo_cli(out, 2, "--noise-sigma", "2")
    assert r.exit_code == 0, r.output
    res = read_stereo(out)
    assert res.settings["noise_sigma"] == 2.0 and StereoOptions.from_settings(res.settings).noise_sigma == 2.0
    f1 = res.fields[1]
    assert np.all(f1.details["noise_sigma_grey"] == 2.0)  # given, not estimated: match, left and right track
    assert np.isfinite(f1.details["sigma_uvw_mm"][f1.valid]).all() and np.count_nonzero(f1.valid) > 0
    # the stored sigma reaches the exports (CSV read back with pandas)
    r = CliRunner().invoke(main, ["export", str(out), "--format", "csv", "-o", str(tmp_path / "csv")])
    assert r.exit_code == 0, r.output
    table = pd.read_csv(tmp_path / "csv" / "stereo_000001.csv", index_col="point")
    for name, (key, j) in SIGMA_3D.items():
        want = np.where(f1.valid, f1.details[key][:, j], np.nan)
        assert np.allclose(table[name].to_numpy(), want, rtol=1e-15, atol=0, equal_nan=True)
    r = _stereo_cli(out, 3, "--noise-sigma", "3")
    assert r.exit_code == 1 and "--noise-sigma (noise_sigma): 2.0 in the file, 3.0 now" in " ".join(r.output.split())
    r = _stereo_cli(out, 3, "--noise-sigma", "0")
    assert r.exit_code == 2 and "--noise-sigma" in r.output
    old = _copy("stereo_cli_v1.h5", tmp_path)
    assert "noise_sigma" not in read_stereo(old).settings
    r = _stereo_cli(old, 3, "--noise-sigma", "2", "--order", "2")
    assert r.exit_code == 1 and "--noise-sigma (noise_sigma): none in the file, 2.0 now" in " ".join(r.output.split())
    r = _stereo_cli(old, 3, "--order", "2")  # 8d9f975's default order (1 since issue 25)
    assert r.exit_code == 0, r.output
    assert read_stereo(old).indices == [0, 1, 2]


# -- schema-2 files written before options were added (tests/data/settings_v2: the settings b36e3a0 stored)
V2 = Path(__file__).parents[1] / "data" / "settings_v2"


@pytest.mark.parametrize("record, name, shape", [(TrackOptions, "track_b36e3a0.json", (80, 100)),
                                                 (StereoOptions, "stereo_b36e3a0.json", (96, 128))])
def test_schema2_file_without_later_options_still_resumes(record, name, shape):
    """A schema-2 file written before an option existed reads that option as the behaviour it had
    (``ADDED_OPTIONS``) and resumes with a run given those values; every other stored value survives."""
    import json
    stored = json.loads((V2 / name).read_text())
    read = record.from_settings(stored)
    assert {k: v for k, v in read.to_settings().items() if k in stored} == stored
    same_run = record.from_keywords({**{k: v for k, v in stored.items() if k != "options_schema"},
                                     **record.ADDED_OPTIONS}, shape=shape)
    assert read.differences(same_run) == [] and same_run.resume_check(stored) is None
    later = set(same_run.to_settings()) - set(stored)
    assert later == set(record.ADDED_OPTIONS), "a new option needs its old behaviour in ADDED_OPTIONS"


def test_a_stored_robust_false_means_off_and_the_cli_robust_options(tmp_path):
    """``robust`` became ``"adaptive"`` by default (issue 26): a file that stores ``robust: false`` (every
    schema-2 file before it, and schema-1 files, which wrote it only when on) reads as off, resumes with
    ``--robust-mode off`` / ``robust=False``, and a resume with the new default is refused naming the option."""
    import json

    from dic.commands._robust import robust_value

    stored = json.loads((V2 / "track_b36e3a0.json").read_text())
    read = TrackOptions.from_settings(stored)
    assert read.robust is False and read.check_outliers is False
    assert StereoOptions.from_settings(json.loads((V2 / "stereo_b36e3a0.json").read_text())).robust is False
    # (with the options added since, at their old behaviour: TrackOptions.ADDED_OPTIONS)
    given = {**{k: v for k, v in stored.items() if k != "options_schema"}, **TrackOptions.ADDED_OPTIONS}
    assert TrackOptions.from_keywords({**given, "robust": False}, shape=(80, 100)).resume_check(stored) is None
    refusal = TrackOptions.from_keywords({**given, "robust": "adaptive", "check_outliers": False},
                                         shape=(80, 100)).resume_check(stored)
    assert "--robust/--robust-mode (robust): False in the file, 'adaptive' now" in refusal
    assert StereoOptions().robust is False  # stereo stays plain by default (docs/dic2d.md, Robust correlation)
    # the three values in the record and in the file
    for value in (False, True, "adaptive"):
        assert TrackOptions.from_settings(TrackOptions(robust=value).to_settings()).robust == value
        assert StereoOptions.from_settings(StereoOptions(robust=value).to_settings()).robust == value
    # the command line: --robust keeps its meaning (on), --robust-mode chooses; specula track's default is adaptive
    # (specula stereo's off)
    assert robust_value(False, None, default="off") is False
    assert [robust_value(False, None, default="adaptive"), robust_value(True, None), robust_value(False, "off"),
            robust_value(False, "on"), robust_value(True, "on"), robust_value(False, "adaptive")] == \
        ["adaptive", True, False, True, True, "adaptive"]
    out = tmp_path / "off.h5"
    r = _track_cli(out, ["f1"], "--robust-mode", "off")
    assert r.exit_code == 0, r.output
    assert read_results(out).settings["robust"] is False
    r = _track_cli(tmp_path / "x.h5", ["f1"], "--robust", "--robust-mode", "adaptive")
    assert r.exit_code == 2 and "--robust means --robust-mode on" in " ".join(r.output.split())
    r = _track_cli(tmp_path / "y.h5", ["f1"], "--robust-mode", "sometimes")
    assert r.exit_code == 2 and "--robust-mode" in r.output
    default = tmp_path / "default.h5"
    assert _track_cli(default, ["f1"]).exit_code == 0
    res = read_results(default)
    assert res.settings["robust"] == "adaptive" and res.settings["check_outliers"] is True
    assert "robust_refined" in res.frames[1].attrs  # the points refined by robust IC-GN, counted per frame


def test_stereo_motion_prediction_is_recorded_and_kept_on_resume(tmp_path):
    """--motion-prediction: recorded; a resume that does not give it keeps the file's (library and CLI alike), one
    that gives another value is refused; a new file gets "velocity"."""
    out = tmp_path / "m.h5"
    r = _stereo_cli(out, 2, "--motion-prediction", "none")
    assert r.exit_code == 0, r.output
    assert read_stereo(out).settings["motion_prediction"] == "none"
    stereo_sequence(RIG, _pairs(3), out, step=20, device="cpu")  # the library, not given: the file's own
    back = read_stereo(out)
    assert back.indices == [0, 1, 2] and back.settings["motion_prediction"] == "none"
    r = _stereo_cli(out, 3, "--motion-prediction", "velocity")
    text = " ".join(r.output.split())
    assert r.exit_code == 1 and "--motion-prediction (motion_prediction): 'none' in the file, 'velocity' now" in text
    fresh = tmp_path / "v.h5"
    r = _stereo_cli(fresh, 2)
    assert r.exit_code == 0, r.output
    assert read_stereo(fresh).settings["motion_prediction"] == "velocity"  # a new file: the default
    r = _stereo_cli(fresh, 3)  # the CLI, not given: the file's own
    assert r.exit_code == 0, r.output
    assert read_stereo(fresh).indices == [0, 1, 2]
    r = _stereo_cli(tmp_path / "bad.h5", 2, "--motion-prediction", "linear")
    assert r.exit_code == 2 and "linear" in r.output

"""Re-verification of a stereo sequence's composed tracks against the reference pair (``verify_composed``,
dic.correlation.stereo_verify; issue 26 item 4), against exact truth.

Scene: the virtual lab of tests/dic/test_stereo_sequence.py (4 states, translation and stretch, exact 3-D
displacement known), ``reference="incremental"``: state 2 is tracked from state 1's pair and state 3 from
state 2's, each composed back to the reference pair.
"""
import numpy as np
import pytest
from click.testing import CliRunner
from test_stereo_sequence import STEP, _exact_uvw, lab  # noqa: F401  (lab: the module's fixture)

import dic._stereo as stereo_module
from dic.field3d import StereoStatus
from dic.sequence import stereo_sequence
from dic.sequence.options import StereoOptions
from dic.store import read_stereo

MISMATCH = int(StereoStatus.COMPOSED_MISMATCH)
ARRAYS = ("points", "status", "U", "V", "W", "X", "Y", "Z", "exx", "eyy", "exy", "zncc_left", "zncc_right",
          "strain_valid")


def _error_mm(lab, f):  # noqa: F811
    """|measured - exact| 3-D displacement (mm) at every point (NaN where not valid)."""
    return np.linalg.norm(f.uvw - _exact_uvw(lab, f), axis=1)


def test_a_clean_sequence_is_unchanged_by_the_check(lab, tmp_path):  # noqa: F811
    """No wrong match: no point fails in either camera, and every array of every state is that of the run
    without the check (the check changes nothing when nothing fails). On by default with a moved reference."""
    pairs = list(lab["states"])
    s = stereo_sequence(lab["rig"], pairs, tmp_path / "on.h5", reference="incremental", step=STEP, device="cpu")
    stereo_sequence(lab["rig"], pairs, tmp_path / "off.h5", reference="incremental", step=STEP, device="cpu",
                    verify_composed=False)
    on, off = read_stereo(tmp_path / "on.h5"), read_stereo(tmp_path / "off.h5")
    assert on.settings["verify_composed"] is True and on.settings["verify_zncc"] == 0.95
    assert off.settings["verify_composed"] is False and off.settings["verify_zncc"] is None
    assert s.n_mismatch.tolist() == [0, 0, 0, 0]
    for k in on.indices:
        for name in ARRAYS:
            assert np.array_equal(getattr(on.fields[k], name), getattr(off.fields[k], name), equal_nan=True), (k, name)
        if k >= 2:
            assert _frame_attrs(tmp_path / "on.h5", k)["composed_mismatch"] == 0
            assert "composed_mismatch" not in _frame_attrs(tmp_path / "off.h5", k)  # composed states: every accepted track checked, the lowest ZNCC well above 0.95
            zl, zr = on.fields[k].details["composed_zncc_left"], on.fields[k].details["composed_zncc_right"]
            valid = on.fields[k].valid
            assert np.all(np.isfinite(zl[valid])) and np.nanmin(zl[valid]) > 0.96
            assert np.all(np.isfinite(zr[valid])) and np.nanmin(zr[valid]) > 0.96
        else:  # measured against the reference pair: not composed, not checked
            assert "composed_zncc_left" not in on.fields[k].details


def _corrupted_measure(blocks: dict):
    """StereoCorrelation.measure that reports, for state 1 (tracked from the reference pair), a 4 x 4 block
    of POIs 1 px off in the LEFT track's u and another 4 x 4 block 1 px off in the RIGHT track's u: wrong
    matches that anchor the reference moved to state 1 (incremental)."""
    measure = stereo_module.StereoCorrelation.measure

    def corrupted(self, left, right, *, index=1, **kw):
        f = measure(self, left, right, index=index, **kw)
        if index == 1:
            xs, ys = np.unique(f.points[:, 0]), np.unique(f.points[:, 1])

            def block(i, j):
                return np.flatnonzero(np.isin(f.points[:, 0], xs[i:i + 4]) & np.isin(f.points[:, 1], ys[j:j + 4]))

            blocks["left"], blocks["right"] = block(2, 3), block(len(xs) - 7, 3)
            assert f.valid[blocks["left"]].all() and f.valid[blocks["right"]].all()
            f.details["params_left"][blocks["left"], 0] += 1.0
            f.details["params_right"][blocks["right"], 0] += 1.0
        return f

    return corrupted


def test_a_wrong_match_carried_by_a_reference_update_is_flagged_per_camera(lab, tmp_path, monkeypatch):  # noqa: F811
    """Without the check, states 2 and 3 inherit the wrong matches of state 1 (valid, about 2 mm off). With it,
    every point of state 2 more than 1.5 mm off fails and none within 0.2 mm does; the left camera's failures
    are in the left-corrupted block, the right camera's in the right-corrupted block; the counts are in the file
    and the summary. The failed points anchor nothing: state 3 (tracked from state 2) is on the exact field."""
    blocks = {}
    monkeypatch.setattr(stereo_module.StereoCorrelation, "measure", _corrupted_measure(blocks))
    pairs = list(lab["states"])
    plain = tmp_path / "plain.h5"
    stereo_sequence(lab["rig"], pairs, plain, reference="incremental", step=STEP, device="cpu", verify_composed=False)
    res = read_stereo(plain)
    both = np.concatenate([blocks["left"], blocks["right"]])
    for k in (2, 3):  # the problem, shown
        err = _error_mm(lab, res.fields[k])
        assert np.count_nonzero(res.fields[k].valid[both] & (err[both] > 1.5)) >= 24, (k, err[both])

    checked = tmp_path / "checked.h5"
    s = stereo_sequence(lab["rig"], pairs, checked, reference="incremental", step=STEP, device="cpu")
    res = read_stereo(checked)
    by_state = dict(zip(s.indices.tolist(), s.n_mismatch.tolist()))
    assert by_state[0] == by_state[1] == 0
    f = res.fields[2]
    flagged = f.status == MISMATCH
    err = _error_mm(lab, f)
    # the error a flagged point would have had: its reported tracks, triangulated (the plain run's state 2)
    err_plain = _error_mm(lab, read_stereo(plain).fields[2])
    reported = f.valid | flagged
    assert not np.any(f.valid & flagged)
    assert np.all(flagged[reported & (err_plain > 1.5)]), np.flatnonzero(reported & (err_plain > 1.5) & ~flagged)
    assert not np.any(flagged & (err_plain < 0.2)), np.flatnonzero(flagged & (err_plain < 0.2))
    assert np.nanmax(err[f.valid]) < 1.2  # (a corner of a block, placed from half-wrong neighbours: ~1 mm, ZNCC 0.95)
    assert np.count_nonzero(np.isin(np.flatnonzero(flagged), both)) >= 24
    zl, zr = f.details["composed_zncc_left"], f.details["composed_zncc_right"]
    fail_left, fail_right = np.flatnonzero(zl < 0.95), np.flatnonzero(zr < 0.95)
    assert set(fail_left) <= set(blocks["left"]) and len(fail_left) >= 12  # each camera's failures: its own block
    assert set(fail_right) <= set(blocks["right"]) and len(fail_right) >= 12
    attrs = _frame_attrs(checked, 2)
    assert attrs["composed_mismatch"] == np.count_nonzero(flagged) == by_state[2]
    assert attrs["composed_mismatch_left"] == len(fail_left) and attrs["composed_mismatch_right"] == len(fail_right)
    # state 3, tracked from state 2 where the failed points anchor nothing: every valid point on the exact field
    f3 = res.fields[3]
    assert np.nanmax(_error_mm(lab, f3)[f3.valid]) < 0.15
    assert np.count_nonzero(f3.valid[both]) >= 16  # points of the blocks placed by their neighbours, tracked again
    assert _frame_attrs(checked, 3)["composed_mismatch"] == by_state[3] == np.count_nonzero(f3.status == MISMATCH)


def _frame_attrs(path, k) -> dict:
    import h5py

    from dic.store.layout import frame_name

    with h5py.File(path, "r") as h:
        return dict(h[f"frames/{frame_name(k)}"].attrs)


def test_options_and_cli(lab, tmp_path):  # noqa: F811
    assert StereoOptions().verify_composed is None and StereoOptions().verify_zncc is None  # fixed: cannot act
    assert StereoOptions(reference="every:2").verify_composed is True
    assert StereoOptions(reference="every:2").verify_zncc == 0.95
    assert StereoOptions(reference="incremental", verify_composed=False, verify_zncc=0.9).verify_zncc is None
    assert StereoOptions(reference="incremental", verify_zncc=0.97).verify_zncc == 0.97
    from dic.cli import main
    from dic.io import write_image

    pairs = list(lab["states"])[:3]
    paths = []
    for k, (a, b) in enumerate(pairs):
        for side, img in (("L", a), ("R", b)):
            paths.append(str(tmp_path / f"{side}{k}.png"))
            write_image(paths[-1], img)
    lab["rig"].save(tmp_path / "rig.json")
    base = ["stereo", "--rig", str(tmp_path / "rig.json"), *paths, "--step", str(STEP), "--device", "cpu"]
    runner = CliRunner()
    r = runner.invoke(main, [*base, "-o", str(tmp_path / "s.h5"), "--reference", "incremental", "--verify-zncc", "0.97"])
    assert r.exit_code == 0, r.output
    assert "state 2: " in r.output and "0 failed the check against the reference pair" in r.output
    assert "composed tracks checked against the reference pair in 1 state(s): 0 point(s) failed (ZNCC < 0.97)" \
        in r.output
    res = read_stereo(tmp_path / "s.h5")
    assert res.settings["verify_composed"] is True and res.settings["verify_zncc"] == 0.97
    assert _frame_attrs(tmp_path / "s.h5", 2)["composed_mismatch"] == 0
    assert "composed_mismatch" not in _frame_attrs(tmp_path / "s.h5", 1)
    r = runner.invoke(main, [*base, "-o", str(tmp_path / "x.h5"), "--verify-zncc", "0.9", "--no-verify-composed"])
    assert r.exit_code == 2 and "--verify-zncc cannot act with --no-verify-composed" in r.output
    r = runner.invoke(main, [*base, "-o", str(tmp_path / "n.h5"), "--reference", "incremental",
                             "--no-verify-composed", "--no-right-track-mask", "-q"])
    assert r.exit_code == 0, r.output
    assert read_stereo(tmp_path / "n.h5").settings["verify_composed"] is False
    assert read_stereo(tmp_path / "n.h5").settings["right_track_mask"] is False  # (tests/dic/test_stereo_masks.py)
    assert res.settings["right_track_mask"] is True
    # a file written with the check resumes only with it (and the other way round): named in the refusal
    with pytest.raises(ValueError, match=r"--verify-composed \(verify_composed\): False in the file, True now"):
        stereo_sequence(lab["rig"], pairs, tmp_path / "n.h5", reference="incremental", step=STEP, device="cpu")

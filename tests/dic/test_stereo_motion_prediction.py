"""The temporal tracks' constant-velocity start (StereoCorrelation(motion_prediction="velocity")): kept when its
first pass accepts the points the state before had, else started again from the previous state + the global shift.

Scene: two 320x240 px cameras 300 mm apart and a speckled plane at 1000 mm (the virtual lab of
tests/dic/test_stereo_sequence.py) moved by the same rigid translation at every state (0.5 px to 1 px in the
images) for states 0..4, then by a jump of about 9 px (state 5): a smooth motion, then one the constant-velocity
prediction gets wrong.
"""
from dataclasses import replace

import numpy as np
import pytest
from test_stereo_sequence import _cameras

from dic._stereo import StereoCorrelation, _predicted_start
from dic.lab import Displacement, Scene, SpecklePlane, render, stereo_rig
from dic.synth import make_speckle

STEP_MM = np.array([0.8, -0.5, 1.5])  # world translation per state, states 0..4
JUMP_MM = np.array([12.0, 0.0, 0.0])   # added at state 5
N_STATES = 6


@pytest.fixture(scope="module")
def lab():
    cams = _cameras()  # the stereo sequence tests' two 320x240 px cameras
    speckle = make_speckle(region=(-5, -5, 305, 255), radius=1.2, density=0.5, bits=None, seed=3)
    plane = SpecklePlane.facing(center=(0.0, 0.0, 1000.0), normal=(0.0, 0.0, -1.0), size=(300.0, 250.0),
                                speckle=speckle)
    pairs = []
    for k in range(N_STATES):
        t_world = min(k, 4) * STEP_MM + (JUMP_MM if k == 5 else 0.0)
        t_local = plane.R_world_surface.T @ t_world
        disp = Displacement(np.broadcast_to(t_local, (2, 2, 3)).copy(), (0.0, 0.0), (300.0, 250.0))
        scene = Scene(cameras=cams, planes=[replace(plane, displacement=disp)])
        pairs.append(tuple(render(scene, i, samples=16, seed=10 * k + i) for i in range(2)))
    return {"rig": stereo_rig(*cams), "pairs": pairs}


def _run(lab, prediction, monkeypatch):
    """Every state measured in order; per state and camera the first pass's guess, the previous parameters, the
    prediction and the track's result."""
    seen = []
    original = StereoCorrelation._track

    def spy(self, corr, image, previous, eligible, *args, predicted=None, **kw):
        guesses = []
        run_frame = corr.run_frame

        def recording(frame, guess, **k):
            guesses.append(np.array(guess))
            return run_frame(frame, guess, **k)

        corr.run_frame = recording  # this call's only (an instance attribute, deleted below)
        try:
            res = original(self, corr, image, previous, eligible, *args, predicted=predicted, **kw)
        finally:
            del corr.run_frame
        seen.append({"side": kw["side"], "guess": guesses[-1], "guesses": guesses, "previous": previous,
                     "predicted": predicted, "result": res, "eligible": eligible})
        return res

    monkeypatch.setattr(StereoCorrelation, "_track", spy)
    pairs = lab["pairs"]
    sc = StereoCorrelation(lab["rig"], *pairs[0], step=12, motion_prediction=prediction, device="cpu")
    fields = [sc.measure(*pairs[k], index=k) for k in range(1, N_STATES)]
    monkeypatch.undo()
    assert len(seen) == 2 * len(fields)
    states = [seen[2 * i:2 * i + 2] for i in range(len(fields))]  # states 1..5: (left, right)
    return fields, states


def _uv(p):
    return p[:, [0, 3]]  # 1st order: u, v


def test_constant_velocity_starts_next_to_the_result_and_takes_fewer_iterations(lab, monkeypatch):
    fields_v, states_v = _run(lab, "velocity", monkeypatch)
    fields_n, states_n = _run(lab, "none", monkeypatch)
    # state 1 starts from the reference pair (no state before it): no prediction
    assert all(t["predicted"] is None for t in states_v[0])
    # state 2: the reference pair's zero is the state before state 1, so the prediction is twice state 1's result
    for t in states_v[1]:
        rows = np.all(np.isfinite(t["predicted"]), axis=1)
        assert np.count_nonzero(rows) > 100
        np.testing.assert_array_equal(t["predicted"][rows], 2.0 * t["previous"][rows])
        np.testing.assert_array_equal(rows & t["eligible"], np.all(np.isfinite(t["previous"]), axis=1) & t["eligible"])
    for state in (2, 3, 4):  # constant velocity: the prediction is (almost) the result
        for t_v, t_n in zip(states_v[state - 1], states_n[state - 1]):
            r = t_v["result"]
            ok = r.accepted
            assert t_v["predicted"] is not None and np.count_nonzero(ok) > 100
            assert len(t_v["guesses"]) == 1  # the prediction held: one first pass, no global shift
            err_pred = np.abs(_uv(t_v["guess"][ok]) - _uv(r.params[ok]))
            err_prev = np.abs(_uv(np.nan_to_num(t_v["previous"][ok])) - _uv(r.params[ok]))
            assert np.median(err_pred) < 0.05, (state, t_v["side"])          # px
            assert np.median(np.max(err_prev, axis=1)) > 0.4, (state, t_v["side"])  # the step from the state before
            # ... and IC-GN converges in fewer iterations than from the previous state + the global shift
            it_v = np.mean(r.iterations[ok])
            it_n = np.mean(t_n["result"].iterations[t_n["result"].accepted])
            assert it_v < it_n - 0.5, (state, t_v["side"], it_v, it_n)
    # the same measurement: both starts converge to the same warps (IC-GN's tolerance, 1e-3 px)
    for fv, fn in zip(fields_v, fields_n):
        both = fv.valid & fn.valid
        assert np.count_nonzero(both) >= 0.95 * np.count_nonzero(fn.valid)
        assert np.nanmax(np.abs(fv.xyz[both] - fn.xyz[both])) < 0.02  # mm (depth: ~3 mm per px of disparity)


def test_a_jump_the_global_shift_sees_starts_from_the_previous_state(lab, monkeypatch):
    fields, states = _run(lab, "velocity", monkeypatch)
    for t in states[4]:  # state 5: predicted ~1 px, the images moved ~9 px
        assert t["predicted"] is not None
        # the first pass from the prediction accepted too few points: a second one from the previous state + the shift
        assert len(t["guesses"]) == 2
        rows = t["eligible"] & np.all(np.isfinite(t["previous"]), axis=1)
        np.testing.assert_array_equal(t["guesses"][0][rows], t["predicted"][rows])
        step = _uv(t["guess"][rows]) - _uv(t["previous"][rows])
        shift = np.round(np.median(step, axis=0))
        assert abs(shift[0]) >= 6  # the global shift was applied ...
        np.testing.assert_array_equal(step, np.broadcast_to(shift, step.shape))  # ... to the previous state
    last = fields[-1]
    assert np.count_nonzero(last.valid) >= 0.9 * np.count_nonzero(fields[0].valid)


def test_predicted_start_fills_rows_without_a_prediction_with_the_median_step():
    prior = np.array([[1.0, 0.1, 0.0, 2.0, 0.0, 0.1], [5.0, 0.0, 0.0, 5.0, 0.0, 0.0], [0.0] * 6, [3.0] * 6])
    predicted = prior.copy()
    predicted[[0, 1], 0] += [0.8, 1.0]  # u steps 0.8, 1.0
    predicted[[0, 1], 3] += [-0.4, -0.6]  # v steps -0.4, -0.6
    predicted[2:] = np.nan  # no prediction (a point the state before lacked)
    tracked = np.array([True, True, True, False])
    g = _predicted_start(prior, predicted, tracked, 6)
    np.testing.assert_array_equal(g[:2], predicted[:2])
    np.testing.assert_allclose(g[2], [0.9, 0.0, 0.0, -0.5, 0.0, 0.0])  # prior + the median step
    np.testing.assert_allclose(g[3], prior[3] + [0.9, 0, 0, -0.5, 0, 0])
    assert _predicted_start(prior, np.full_like(prior, np.nan), tracked, 6) is None  # nothing predicted


def test_motion_prediction_is_checked():
    with pytest.raises(ValueError, match="motion_prediction must be one of"):
        StereoCorrelation(None, np.zeros((8, 8)), np.zeros((8, 8)), motion_prediction="linear")

"""N-step phase demodulation kernel (kernels/phase.py) against exact fringes and a NumPy reference."""
import numpy as np
import pytest

from kernels.phase import demodulate, demodulation_matrix, equal_phase_shifts


def _wrap(a):
    return (a + np.pi) % (2 * np.pi) - np.pi


@pytest.mark.parametrize("steps", [3, 4, 7])
def test_exact_on_synthetic_fringes(device, rng, steps):
    h, w = 37, 53
    phi = rng.uniform(-np.pi, np.pi, (h, w))
    amp = rng.uniform(5, 120, (h, w))
    bg = rng.uniform(50, 200, (h, w))
    shifts = equal_phase_shifts(steps)
    stack = bg + amp * np.sin(phi + shifts[:, None, None])
    p, m, b, v = [a.numpy() for a in demodulate(stack, device=device)]
    # float32 images of values <= 320: relative rounding 6e-8 -> errors ~1e-5 grey levels, the phase
    # error ~ 1e-5 / amp <= 2e-6 rad; 1e-4 leaves room for the float32 sums
    assert np.max(np.abs(_wrap(p - phi))) < 1e-4
    assert np.max(np.abs(m - amp)) < 1e-3
    assert np.max(np.abs(b - bg)) < 1e-3
    assert v.all()


def test_matches_numpy_atan2_reference(device, rng):
    # an independent reference: the classic N-step formula with sine/cosine sums
    stack = rng.uniform(0, 255, (5, 24, 31))
    d = 2 * np.pi * np.arange(5) / 5
    s = np.tensordot(np.cos(d), stack, axes=1)
    c = np.tensordot(np.sin(d), stack, axes=1)
    ref_phase = np.arctan2(s, c)
    ref_mod = 2 / 5 * np.hypot(s, c)
    p, m, b, _ = [a.numpy() for a in demodulate(stack, device=device)]
    # float32 accumulation of 5 values <= 255: ~1e-4 grey levels; phase error <= 1e-4 / mod,
    # bounded where the modulation exceeds 1 grey level
    big = ref_mod > 1
    assert np.max(np.abs(_wrap(p - ref_phase))[big]) < 1e-3
    assert np.max(np.abs(m - ref_mod)) < 1e-3
    assert np.max(np.abs(b - stack.mean(axis=0))) < 1e-3


def test_arbitrary_shifts(device, rng):
    shifts = np.array([0.0, 1.1, 2.0, 3.7, 5.0])
    phi = rng.uniform(-np.pi, np.pi, (16, 16))
    stack = 100 + 50 * np.sin(phi + shifts[:, None, None])
    p, m, _, _ = [a.numpy() for a in demodulate(stack, phase_shifts=shifts, device=device)]
    assert np.max(np.abs(_wrap(p - phi))) < 1e-4  # exact least squares, float32 rounding only
    assert np.max(np.abs(m - 50)) < 1e-3


def test_validity_mask(device):
    stack = np.full((4, 4, 5), 100, dtype=np.uint8)
    stack[:, 0, 0] = [100, 140, 100, 60]   # modulation 40
    stack[:, 1, 1] = [100, 102, 100, 98]   # modulation 2
    stack[:, 2, 2] = [255, 140, 100, 60]   # saturated sample
    p, m, b, v = [a.numpy() for a in demodulate(stack, min_modulation=5.0, device=device)]
    assert v[0, 0] == 1
    assert v[1, 1] == 0            # modulation 2 < 5
    assert v[2, 2] == 0            # uint8 input: 255 counts as saturated
    assert v[3, 3] == 0            # flat
    assert abs(m[0, 0] - 40) < 1e-3


def test_out_arrays_reused(device, rng):
    import warp as wp

    stack = rng.uniform(0, 255, (4, 8, 9)).astype(np.float32)
    out = (wp.empty((8, 9), dtype=wp.float32, device=device), wp.empty((8, 9), dtype=wp.float32, device=device),
           wp.empty((8, 9), dtype=wp.float32, device=device), wp.empty((8, 9), dtype=wp.uint8, device=device))
    res = demodulate(stack, out=out, device=device)
    assert all(a is b for a, b in zip(res, out))


def test_bad_input(device):
    with pytest.raises(ValueError, match="stack"):
        demodulate(np.zeros((10, 10)), device=device)
    with pytest.raises(ValueError, match="N >= 3"):
        demodulate(np.zeros((2, 10, 10)), device=device)
    with pytest.raises(ValueError, match="one shift per image"):
        demodulate(np.zeros((4, 10, 10)), phase_shifts=[0, 1, 2], device=device)
    with pytest.raises(ValueError, match="NaN"):
        demodulate(np.full((3, 4, 4), np.nan), device=device)
    with pytest.raises(ValueError, match="same shape"):
        demodulate([np.zeros((4, 4)), np.zeros((4, 5)), np.zeros((4, 4))], device=device)
    with pytest.raises(ValueError, match="degenerate"):
        demodulation_matrix([0.0, 0.0, 2 * np.pi])
    with pytest.raises(ValueError, match="integer >= 3"):
        equal_phase_shifts(2)
    with pytest.raises(ValueError, match="min_modulation"):
        demodulate(np.zeros((3, 4, 4)), min_modulation=-1, device=device)

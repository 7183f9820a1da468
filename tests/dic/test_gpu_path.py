"""The GPU path (issue 13, item 7), checked on CPU tensors: frames given as torch tensors are read in place by
the sequence engine (no host copy of a frame, no SHA-256 of its bytes: a checksum computed on the device), with
results bitwise those of the same frames given as NumPy arrays; resume works across the two kinds of digest."""
import importlib

import numpy as np
import pytest

from dic.sequence import track_sequence
from dic.store import DEVICE_CHECKSUM_PREFIX, device_checksum, image_digest, read_results
from dic.synth import speckle_pair

torch = pytest.importorskip("torch")

SHAPE = (80, 96)
N = 6


@pytest.fixture(scope="module")
def frames():
    ref, _ = speckle_pair(SHAPE, (0, 0), seed=5)
    return ref, [speckle_pair(SHAPE, (0.3 * k, -0.2 * k), seed=5)[1] for k in range(1, N + 1)]


def _same(a, b):
    ra, rb = read_results(a), read_results(b)
    assert sorted(ra.frames) == sorted(rb.frames)
    for k in ra.frames:
        for name in ("u", "v", "params", "zncc", "status", "valid", "sigma_u", "sigma_v"):
            assert np.array_equal(getattr(ra.frames[k], name), getattr(rb.frames[k], name), equal_nan=True), (k, name)


@pytest.fixture
def no_host_copy_of_tensors(monkeypatch):
    """Fail if a tensor frame goes through the host-side array check or the SHA-256 digest; only a frame that
    becomes a reference may be copied to the host (once: the reference is prepared there), counted in the list."""
    import dic.store.layout
    import kernels.images

    to_host = []

    def guard(original, what):
        def wrapped(image, *args, **kwargs):
            if isinstance(image, torch.Tensor):
                name = args[0] if args else kwargs.get("name", "")
                if what != "as_float32_image" or name != "a new reference":
                    raise AssertionError(f"a tensor frame went through {what} ({name})")
                to_host.append(tuple(image.shape))
            return original(image, *args, **kwargs)
        return wrapped

    for module in (kernels.images, importlib.import_module("kernels.icgn"), importlib.import_module("dic._track")):
        monkeypatch.setattr(module, "as_float32_image", guard(kernels.images.as_float32_image, "as_float32_image"))
    monkeypatch.setattr(dic.store.layout, "image_digest", guard(dic.store.layout.image_digest, "image_digest"))
    monkeypatch.setattr(importlib.import_module("dic.store"), "image_digest",
                        guard(dic.store.layout.image_digest, "image_digest"))
    return to_host


def test_device_checksum_same_for_tensor_and_array_and_tells_images_apart(frames):
    ref, cur = frames[0], frames[1][0]
    d = device_checksum(ref)
    assert d.startswith(DEVICE_CHECKSUM_PREFIX) and d == device_checksum(torch.from_numpy(ref))
    assert d == device_checksum(torch.from_numpy(ref.astype(np.uint8)))  # the float32 grey levels decide
    changed = ref.copy()
    changed[40, 50] += 1
    swapped = ref.copy()
    swapped[[3, 4]] = swapped[[4, 3]]
    others = {device_checksum(x) for x in (cur, changed, swapped, ref.reshape(SHAPE[1], SHAPE[0]))}
    assert d not in others and len(others) == 4
    with pytest.raises(ValueError, match="real image"):
        device_checksum(torch.zeros(3, dtype=torch.complex64))


@pytest.mark.parametrize("reference", ["fixed", "incremental"])
def test_tensor_frames_are_read_in_place_with_identical_results(frames, tmp_path, reference,
                                                                no_host_copy_of_tensors):
    ref, cur = frames
    track_sequence(ref, cur, tmp_path / "numpy.h5", reference=reference, step=10, device="cpu")
    tensors = [torch.from_numpy(c) for c in cur]
    track_sequence(ref, tensors, tmp_path / "torch.h5", reference=reference, step=10, device="cpu")
    _same(tmp_path / "numpy.h5", tmp_path / "torch.h5")
    # fixed: no frame leaves the device; incremental: each frame that becomes a reference, once
    assert len(no_host_copy_of_tensors) == (0 if reference == "fixed" else N - 1)
    stored = read_results(tmp_path / "torch.h5").frames[2].attrs["sha256"]
    assert stored == device_checksum(cur[1])
    # 8-bit tensors, converted on the device: the same grey levels, the same results
    track_sequence(ref, [t.to(torch.uint8) for t in tensors], tmp_path / "u8.h5", reference=reference, step=10,
                   device="cpu")
    _same(tmp_path / "numpy.h5", tmp_path / "u8.h5")


def test_resume_across_tensor_and_array_frames(frames, tmp_path):
    ref, cur = frames
    tensors = [torch.from_numpy(c) for c in cur]
    full = tmp_path / "full.h5"
    track_sequence(ref, cur, full, step=10, device="cpu")
    # begun with tensors (device checksums), resumed with arrays
    a = tmp_path / "a.h5"
    track_sequence(ref, tensors[:3], a, step=10, device="cpu")
    s = track_sequence(ref, cur, a, step=10, device="cpu")
    assert s.skipped == 3 and len(s.frames) == N - 3
    _same(full, a)
    # begun with arrays (SHA-256), resumed with tensors
    b = tmp_path / "b.h5"
    track_sequence(ref, cur[:3], b, step=10, device="cpu")
    s = track_sequence(ref, tensors, b, step=10, device="cpu")
    assert s.skipped == 3
    _same(full, b)
    assert read_results(b).frames[1].attrs["sha256"] == image_digest(cur[0])
    assert read_results(b).frames[5].attrs["sha256"] == device_checksum(cur[4])
    # another image for a finished frame is refused, whatever the kind of digest
    wrong = list(tensors)
    wrong[1] = torch.from_numpy(cur[2])
    for path in (a, b):
        with pytest.raises(ValueError, match="images differ"):
            track_sequence(ref, wrong, path, step=10, device="cpu")

"""segment_drivable on any input, the synthetic scenes, and the public API list."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import scmr_mesh.imaging as imaging
from scmr_mesh.errors import InputError
from scmr_mesh.imaging import DrivableResult, segment_drivable, warm_up
from scmr_mesh.imaging.evaluate import bottom_half_mask, score
from scmr_mesh.imaging.synthetic import SCENE_KINDS, make_scene

PUBLIC = {
    "decode_image", "load_image", "resize_frame", "encode_png", "segment_drivable", "DrivableResult",
    "warm_up", "gaussian_blur_3x3", "srm", "roi", "dominant_channel", "histogram", "otsu_threshold",
    "sobel_magnitude", "remove_sparse_pixels", "red_green", "overlay",
}


def test_public_api_is_reexported():
    assert PUBLIC <= set(imaging.__all__)
    for name in imaging.__all__:
        assert getattr(imaging, name) is not None
    with pytest.raises(AttributeError):
        imaging.no_such_name  # noqa: B018
    import sys

    import scmr_mesh.imaging.srm  # noqa: F401  (must not shadow the function)

    assert imaging.srm is sys.modules["scmr_mesh.imaging.srm"].srm
    from scmr_mesh.imaging import srm

    assert callable(srm) and srm.__name__ == "srm"


def test_warm_up_and_result_shape():
    warm_up()
    img, _ = make_scene("structured_road", seed=0)
    for mode in ("best", "thesis"):
        res = segment_drivable(img, mode=mode, stages=True)
        assert isinstance(res, DrivableResult)
        assert res.mask.shape == (225, 300) and res.mask.dtype == np.uint8
        assert set(np.unique(res.mask)) <= {0, 255}
        assert 0 <= res.threshold <= 255
        assert {"resize", "total", "srm"} <= set(res.timings_ms)
        assert all(v >= 0 for v in res.timings_ms.values())
        st_ = res.stages
        assert st_["srm"].shape == (225, 300, 3) and st_["otsu"].shape == (225, 300)
        assert st_["histogram"].shape == (256,) and st_["histogram"].sum() == (113 - 75) * 100
        assert st_["edges"].shape == (225, 300)
    assert segment_drivable(img).stages is None


def test_unknown_mode_is_a_clear_error():
    with pytest.raises(InputError, match="mode must be one of best, thesis; got 'fast'"):
        segment_drivable(np.zeros((10, 10, 3), np.uint8), mode="fast")


DTYPES = [np.uint8, np.uint8, np.uint8, np.int16, np.float32, np.float64, np.bool_, np.uint16]


@settings(max_examples=40, deadline=None)
@given(
    st.integers(1, 320),
    st.integers(1, 320),
    st.sampled_from([None, 1, 3, 4]),
    st.sampled_from(DTYPES),
    st.integers(0, 2**32 - 1),
    st.sampled_from(["best", "thesis"]),
)
def test_any_size_and_dtype_gives_a_valid_mask_or_a_clear_error(h, w, channels, dtype, seed, mode):
    rng = np.random.default_rng(seed)
    shape = (h, w) if channels is None else (h, w, channels)
    arr = (rng.random(shape) * 255).astype(dtype)
    try:
        res = segment_drivable(arr, mode=mode)
    except InputError as exc:
        assert dtype is not np.uint8  # only non-uint8 arrays are refused here
        assert str(np.dtype(dtype)) in str(exc)
        return
    assert dtype is np.uint8
    assert res.mask.shape == (225, 300) and res.mask.dtype == np.uint8
    assert set(np.unique(res.mask)) <= {0, 255}


@pytest.mark.parametrize("bad", [np.zeros((0, 5, 3), np.uint8), np.zeros((4, 4, 2), np.uint8), np.zeros(5, np.uint8), "img"])
def test_bad_arrays_are_refused(bad):
    with pytest.raises(InputError):
        segment_drivable(bad)


@pytest.mark.parametrize("kind", SCENE_KINDS)
def test_synthetic_scenes_are_seeded_and_exact(kind):
    a, ta = make_scene(kind, seed=4)
    b, tb = make_scene(kind, seed=4)
    c, _ = make_scene(kind, seed=5)
    np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(ta, tb)
    assert not np.array_equal(a, c)
    assert a.shape == (225, 300, 3) and a.dtype == np.uint8
    assert set(np.unique(ta)) == {0, 255}
    assert 0.05 < (ta > 0).mean() < 0.95
    big, tbig = make_scene(kind, seed=1, width=640, height=480)
    assert big.shape == (480, 640, 3) and tbig.shape == (480, 640)


def test_synthetic_scenes_are_not_trivial_and_best_beats_bottom_half():
    """Over the scenes, best beats the bottom-half baseline; no scene is solved perfectly."""
    best, base = [], []
    for kind in SCENE_KINDS:
        for seed in range(2):
            img, truth = make_scene(kind, seed=seed)
            best.append(score(segment_drivable(img).mask, truth)["iou"])
            base.append(score(bottom_half_mask(), truth)["iou"])
    assert np.mean(best) > np.mean(base)
    assert max(best) < 1.0


def test_bad_scene_arguments():
    with pytest.raises(InputError, match="unknown scene kind 'moon'"):
        make_scene("moon")
    with pytest.raises(InputError, match="scene size"):
        make_scene("desert", width=4)

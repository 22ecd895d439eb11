"""The geometry core against OpenCV, torch and hand-computed numbers."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from udh_cli import geometry

SIZES = [(128, 128), (320, 240), (64, 48), (1000, 750)]


def random_offsets(seed: int, width: int, height: int, shape=(4, 2), fraction: float = 0.2) -> np.ndarray:
    """Corner offsets up to ``fraction`` of the smaller side, the range the paper's pairs use."""
    bound = fraction * min(width, height)
    return np.random.default_rng(seed).uniform(-bound, bound, shape)


def smooth_image(width: int, height: int, seed: int = 0, sigma: float = 6.0) -> np.ndarray:
    """(height, width) float32 in [0, 1], blurred noise: smooth, so interpolation differences stay tiny."""
    noise = np.random.default_rng(seed).random((height, width)).astype(np.float32)
    image = cv2.GaussianBlur(noise, (0, 0), sigma)
    return (image - image.min()) / (image.max() - image.min())


def interior(coverage: np.ndarray, margin: int) -> np.ndarray:
    """Boolean mask of ``coverage`` > 0 shrunk by ``margin`` // 2 px, also away from the frame's edges."""
    kernel = np.ones((margin, margin), np.uint8)
    return cv2.erode(coverage, kernel, borderType=cv2.BORDER_CONSTANT, borderValue=0) > 0


# ------------------------------------------------------------------------ 4-point parameterisation


@pytest.mark.parametrize("size", SIZES)
@pytest.mark.parametrize("seed", range(4))
def test_homography_from_offsets_matches_get_perspective_transform(size, seed):
    width, height = size
    offsets = random_offsets(seed, width, height)
    corners = geometry.image_corners(width, height)
    expected = cv2.getPerspectiveTransform(corners.astype(np.float32), (corners + offsets).astype(np.float32))
    # getPerspectiveTransform takes float32 points but solves in float64: compare on the same float32 points.
    offsets32 = (corners + offsets).astype(np.float32).astype(np.float64) - corners.astype(np.float32).astype(np.float64)
    homography = geometry.homography_from_offsets(offsets32, width, height)
    assert homography.shape == (3, 3)
    assert homography[2, 2] == pytest.approx(1.0)
    # OpenCV's own solution hits its four target points only to ~1e-5 px (ours to ~1e-13), so the
    # entries agree to a few 1e-7 relative, and everywhere in the image the two map within 1e-4 px.
    np.testing.assert_allclose(homography, expected / expected[2, 2], rtol=2e-6, atol=1e-12)
    np.testing.assert_allclose(geometry.transform_points(homography, corners), corners + offsets32, atol=1e-9)
    grid = geometry.pixel_grid(width, height)[::7, ::7].reshape(-1, 2)
    np.testing.assert_allclose(geometry.transform_points(homography, grid), cv2.perspectiveTransform(grid[None], expected)[0], atol=1e-4)


@pytest.mark.parametrize("size", SIZES)
@pytest.mark.parametrize("seed", range(4))
def test_offsets_round_trip(size, seed):
    width, height = size
    offsets = random_offsets(seed, width, height)
    homography = geometry.homography_from_offsets(offsets, width, height)
    np.testing.assert_allclose(geometry.offsets_from_homography(homography, width, height), offsets, atol=1e-9)
    # And the other way: a homography survives 3x3 -> 4 points -> 3x3.
    again = geometry.homography_from_offsets(geometry.offsets_from_homography(homography, width, height), width, height)
    np.testing.assert_allclose(again, homography, rtol=1e-9, atol=1e-14)


def test_zero_offsets_give_identity():
    np.testing.assert_allclose(geometry.homography_from_offsets(np.zeros((4, 2)), 320, 240), np.eye(3), atol=1e-12)


def test_offsets_follow_corner_order():
    # Moving only the top-right corner (index 1) by (+7, -3) moves exactly that corner.
    offsets = np.zeros((4, 2))
    offsets[1] = (7.0, -3.0)
    homography = geometry.homography_from_offsets(offsets, 320, 240)
    mapped = geometry.transform_points(homography, geometry.image_corners(320, 240))
    np.testing.assert_allclose(mapped, [[0, 0], [326, -3], [319, 239], [0, 239]], atol=1e-9)


@pytest.mark.parametrize("batch", [(5,), (2, 3), ()])
def test_batched_shapes_match_one_by_one(batch):
    width, height = 128, 96
    offsets = random_offsets(7, width, height, shape=batch + (4, 2))
    homographies = geometry.homography_from_offsets(offsets, width, height)
    assert homographies.shape == batch + (3, 3)
    flat_offsets, flat_h = offsets.reshape(-1, 4, 2), homographies.reshape(-1, 3, 3)
    for one_offsets, one_h in zip(flat_offsets, flat_h):
        np.testing.assert_allclose(one_h, geometry.homography_from_offsets(one_offsets, width, height), atol=1e-12)
    back = geometry.offsets_from_homography(homographies, width, height)
    assert back.shape == batch + (4, 2)
    np.testing.assert_allclose(back, offsets, atol=1e-9)


def test_homography_from_points_general_quadrilaterals():
    rng = np.random.default_rng(3)
    src = np.array([[10.0, 20.0], [300.0, 5.0], [280.0, 230.0], [30.0, 200.0]]) + rng.normal(0, 3, (4, 2))
    dst = src + rng.normal(0, 15, (4, 2))
    expected = cv2.getPerspectiveTransform(src.astype(np.float32), dst.astype(np.float32))
    src, dst = src.astype(np.float32).astype(np.float64), dst.astype(np.float32).astype(np.float64)
    homography = geometry.homography_from_points(src, dst)
    np.testing.assert_allclose(homography, expected / expected[2, 2], rtol=2e-6, atol=1e-12)
    np.testing.assert_allclose(geometry.transform_points(homography, src), dst, atol=1e-9)


def test_small_numpy_batches_take_a_closed_form_equal_to_the_batched_solve():
    rng = np.random.default_rng(4)
    src = rng.uniform(0, 500, (3 * geometry.SMALL_BATCH, 4, 2))
    dst = src + rng.normal(0, 30, src.shape)
    batched = geometry.homography_from_points(src, dst)  # more than SMALL_BATCH pairs: the 8x8 solve
    one_by_one = np.stack([geometry.homography_from_points(s, d) for s, d in zip(src, dst)])
    np.testing.assert_allclose(one_by_one, batched, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(geometry.transform_points(one_by_one, src), dst, atol=1e-8)
    assert geometry.homography_from_points(src[:2].astype(np.float32), dst[:2].astype(np.float32)).dtype == np.float32
    collinear = np.array([[0.0, 0.0], [1.0, 1.0], [2.0, 2.0], [0.0, 5.0]])
    with pytest.raises(np.linalg.LinAlgError):
        geometry.homography_from_points(collinear, geometry.image_corners(2, 2))


# ----------------------------------------------------------------------------------- transforms


@pytest.mark.parametrize("seed", range(3))
def test_transform_points_matches_opencv(seed):
    homography = geometry.homography_from_offsets(random_offsets(seed, 320, 240), 320, 240)
    points = np.random.default_rng(seed).uniform(-50, 400, (200, 2))
    expected = cv2.perspectiveTransform(points[None], homography)[0]
    np.testing.assert_allclose(geometry.transform_points(homography, points), expected, rtol=1e-12, atol=1e-9)


def test_transform_points_broadcasts_over_batches():
    homographies = geometry.homography_from_offsets(random_offsets(1, 64, 64, shape=(6, 4, 2)), 64, 64)  # 6x3x3
    points = np.random.default_rng(1).uniform(0, 63, (10, 2))
    mapped = geometry.transform_points(homographies, points)
    assert mapped.shape == (6, 10, 2)
    np.testing.assert_allclose(mapped[4], cv2.perspectiveTransform(points[None], homographies[4])[0], atol=1e-9)


def test_invert_is_inverse_with_unit_h33():
    homography = geometry.homography_from_offsets(random_offsets(2, 320, 240), 320, 240)
    inverse = geometry.invert(homography)
    assert inverse[2, 2] == pytest.approx(1.0)
    product = homography @ inverse
    np.testing.assert_allclose(product / product[2, 2], np.eye(3), atol=1e-12)


def test_translation():
    np.testing.assert_allclose(geometry.transform_points(geometry.translation(3, -4), np.array([[1.0, 1.0]])), [[4.0, -3.0]])


# ------------------------------------------------------------------------- normalised coordinates


def test_pixel_to_normalized_puts_image_edges_at_plus_minus_one():
    normaliser = geometry.pixel_to_normalized(40, 30)
    edges = np.array([[-0.5, -0.5], [39.5, 29.5], [19.5, 14.5]])  # outer corners of the image, and its centre
    np.testing.assert_allclose(geometry.transform_points(normaliser, edges), [[-1, -1], [1, 1], [0, 0]], atol=1e-12)


@pytest.mark.parametrize(("size_a", "size_b"), [((96, 72), (96, 72)), ((96, 72), (80, 100))])
def test_sampling_grid_with_grid_sample_reproduces_warp_perspective(size_a, size_b):
    torch = pytest.importorskip("torch")
    (w_a, h_a), (w_b, h_b) = size_a, size_b
    image_a = smooth_image(w_a, h_a, seed=1, sigma=3.0)
    b_from_a = geometry.homography_from_offsets(random_offsets(5, w_a, h_a, fraction=0.1), w_a, h_a)
    b_from_a = geometry.rescale_homography(b_from_a, size_a, size_a, size_a, size_b)  # A and B may differ in size
    expected = cv2.warpPerspective(image_a, b_from_a, (w_b, h_b), flags=cv2.INTER_LINEAR)

    grid = geometry.sampling_grid(geometry.invert(b_from_a), size_a, size_b)
    assert grid.shape == (h_b, w_b, 2)
    rendered = torch.nn.functional.grid_sample(
        torch.from_numpy(image_a)[None, None].double(),
        torch.from_numpy(grid)[None],
        mode="bilinear",
        padding_mode="zeros",
        align_corners=False,
    )[0, 0].numpy()
    # Compare where B sees A's interior (border handling differs between the two libraries).
    inside = cv2.warpPerspective(np.ones((h_a, w_a), np.float32), b_from_a, (w_b, h_b), flags=cv2.INTER_NEAREST)
    inside = interior(inside, 5)
    assert inside.sum() > 0.4 * w_b * h_b
    # Measured: ~1.3e-6 of the [0, 1] range (warpPerspective rounds its sampling positions to 1/32 px).
    assert np.abs(rendered - expected)[inside].max() < 1e-4
    # A slip of even 1/20 px in the normalisation shows: it gives ~4.5e-3 here.
    shifted = geometry.sampling_grid(geometry.invert(b_from_a @ geometry.translation(0.05, 0.0)), size_a, size_b)
    wrong = torch.nn.functional.grid_sample(
        torch.from_numpy(image_a)[None, None].double(), torch.from_numpy(shifted)[None], align_corners=False
    )[0, 0].numpy()
    assert np.abs(wrong - expected)[inside].max() > 1e-3


def test_sampling_grid_is_batched():
    homographies = geometry.homography_from_offsets(random_offsets(4, 32, 24, shape=(3, 4, 2), fraction=0.1), 32, 24)
    grids = geometry.sampling_grid(geometry.invert(homographies), (32, 24), (20, 16))
    assert grids.shape == (3, 16, 20, 2)
    np.testing.assert_allclose(grids[2], geometry.sampling_grid(geometry.invert(homographies[2]), (32, 24), (20, 16)), atol=1e-12)


def test_normalized_homography_of_identity_is_identity_and_of_a_shift_is_scaled():
    np.testing.assert_allclose(geometry.normalized_homography(np.eye(3), (64, 48), (64, 48)), np.eye(3), atol=1e-12)
    # A shift of 8 px in a 64-px-wide image is a shift of 2 * 8 / 64 = 0.25 in normalised units.
    shifted = geometry.normalized_homography(geometry.translation(8, 0), (64, 48), (64, 48))
    np.testing.assert_allclose(shifted, geometry.translation(0.25, 0), atol=1e-12)


# --------------------------------------------------------------------------------- torch parity


def test_torch_matches_numpy():
    torch = pytest.importorskip("torch")
    width, height = 128, 96
    offsets = random_offsets(11, width, height, shape=(4, 4, 2))
    h_np = geometry.homography_from_offsets(offsets, width, height)
    h_t = geometry.homography_from_offsets(torch.from_numpy(offsets), width, height)
    assert isinstance(h_t, torch.Tensor) and h_t.dtype == torch.float64 and h_t.shape == (4, 3, 3)
    np.testing.assert_allclose(h_t.numpy(), h_np, rtol=1e-12, atol=1e-14)

    points = np.random.default_rng(11).uniform(0, 127, (4, 30, 2))
    np.testing.assert_allclose(
        geometry.transform_points(h_t, torch.from_numpy(points)).numpy(), geometry.transform_points(h_np, points), atol=1e-10
    )
    np.testing.assert_allclose(
        geometry.offsets_from_homography(h_t, width, height).numpy(), offsets, atol=1e-9
    )
    truth = geometry.homography_from_offsets(offsets[::-1].copy(), width, height)
    for metric in (geometry.mace, geometry.corner_rmse):
        np.testing.assert_allclose(
            metric(h_t, torch.from_numpy(truth), width, height).numpy(), metric(h_np, truth, width, height), rtol=1e-12
        )
    grid_t = geometry.sampling_grid(geometry.invert(h_t), (width, height), (40, 30))
    np.testing.assert_allclose(grid_t.numpy(), geometry.sampling_grid(geometry.invert(h_np), (width, height), (40, 30)), atol=1e-10)


def test_torch_float32_stays_float32_and_accurate():
    torch = pytest.importorskip("torch")
    offsets = random_offsets(12, 128, 128, shape=(8, 4, 2))
    h32 = geometry.homography_from_offsets(torch.from_numpy(offsets).float(), 128, 128)
    assert h32.dtype == torch.float32
    # Hartley normalisation keeps float32 good to well under a hundredth of a pixel at the corners.
    error = geometry.mace(h32.double(), torch.from_numpy(geometry.homography_from_offsets(offsets, 128, 128)), 128, 128)
    assert float(error.max()) < 1e-2


def test_gradcheck_homography_from_offsets():
    torch = pytest.importorskip("torch")
    offsets = torch.tensor(random_offsets(13, 64, 48, shape=(2, 4, 2)), dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda o: geometry.homography_from_offsets(o, 64, 48), (offsets,), eps=1e-6, atol=1e-6)
    # The gradient reaches the loss the network trains on: a corner error.
    truth = torch.from_numpy(geometry.homography_from_offsets(np.zeros((4, 2)), 64, 48))
    geometry.mace(geometry.homography_from_offsets(offsets, 64, 48), truth, 64, 48).sum().backward()
    assert offsets.grad is not None and torch.isfinite(offsets.grad).all() and offsets.grad.abs().sum() > 0


# ------------------------------------------------------------------------------------ resizing

RESIZES = [((320, 240), (160, 120)), ((320, 240), (640, 480)), ((320, 240), (400, 150)), ((301, 203), (97, 411)), ((128, 128), (128, 96))]


@pytest.mark.parametrize(("size_from", "size_to"), RESIZES)
@pytest.mark.parametrize("interpolation", [cv2.INTER_LINEAR, cv2.INTER_CUBIC])
def test_resize_matrix_matches_cv2_resize(size_from, size_to, interpolation):
    # Linear and cubic interpolation reproduce a linear ramp exactly, so resized(x') = ramp(S^-1 x').
    (w, h), (w2, h2) = size_from, size_to
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
    ramp = (0.7 * xs + 1.3 * ys + 5.0).astype(np.float32)
    resized = cv2.resize(ramp, (w2, h2), interpolation=interpolation)
    source_points = geometry.transform_points(
        np.linalg.inv(geometry.resize_matrix(size_from, size_to)), geometry.pixel_grid(w2, h2).reshape(-1, 2)
    ).reshape(h2, w2, 2)
    expected = 0.7 * source_points[..., 0] + 1.3 * source_points[..., 1] + 5.0
    # Only where the interpolation kernel stays inside the source (OpenCV clamps at the border).
    inside = (source_points[..., 0] > 2) & (source_points[..., 0] < w - 3) & (source_points[..., 1] > 2) & (source_points[..., 1] < h - 3)
    assert inside.sum() > 0.5 * w2 * h2
    np.testing.assert_allclose(resized[inside], expected[inside], atol=2e-3 * expected.max())


def test_resize_matrix_is_for_dsize_not_fx():
    # cv2.resize(img, None, fx=f) rounds the output size but samples with f itself; resize_matrix uses
    # the ratio of the sizes, so it describes cv2.resize(img, dsize) (the two differ when w * f is fractional).
    ramp = np.tile(np.arange(321, dtype=np.float32), (10, 1))
    by_fx = cv2.resize(ramp, None, fx=0.5, fy=1.0, interpolation=cv2.INTER_LINEAR)
    by_size = cv2.resize(ramp, (by_fx.shape[1], 10), interpolation=cv2.INTER_LINEAR)
    source_x = geometry.transform_points(np.linalg.inv(geometry.resize_matrix((321, 10), (160, 10))), np.array([[100.0, 0.0]]))
    assert by_size[0, 100] == pytest.approx(source_x[0, 0], abs=1e-3)
    assert by_fx[0, 100] == pytest.approx((100 + 0.5) / 0.5 - 0.5, abs=1e-3)  # 200.5, not 201.13


def test_resize_matrix_matches_cv2_resize_area_downscale():
    # INTER_AREA averages whole boxes on an integer downscale; a ramp's box mean is its value at the box centre.
    ys, xs = np.mgrid[0:240, 0:320].astype(np.float64)
    ramp = (0.7 * xs + 1.3 * ys).astype(np.float32)
    resized = cv2.resize(ramp, (80, 60), interpolation=cv2.INTER_AREA)
    centres = geometry.transform_points(np.linalg.inv(geometry.resize_matrix((320, 240), (80, 60))), geometry.pixel_grid(80, 60))
    np.testing.assert_allclose(resized, 0.7 * centres[..., 0] + 1.3 * centres[..., 1], atol=1e-3)


@pytest.mark.parametrize(("size_a", "size_a_to", "size_b", "size_b_to"), [
    ((320, 240), (160, 120), None, None),
    ((320, 240), (640, 480), None, None),
    ((320, 240), (400, 150), (300, 260), (77, 513)),
    ((1600, 900), (128, 128), (1600, 900), (128, 128)),
])
def test_rescale_homography_maps_resized_pixels_exactly(size_a, size_a_to, size_b, size_b_to):
    b_from_a = geometry.homography_from_offsets(random_offsets(21, *size_a), *size_a)
    rescaled = geometry.rescale_homography(b_from_a, size_a, size_a_to, size_b, size_b_to)
    size_b, size_b_to = size_b or size_a, size_b_to or size_a_to
    # A scene point at p in A is at S_a p in resized A, and at S_b H p in resized B.
    points_a = np.random.default_rng(21).uniform(0, min(size_a) - 1, (50, 2))
    in_resized_a = geometry.transform_points(geometry.resize_matrix(size_a, size_a_to), points_a)
    in_resized_b = geometry.transform_points(geometry.resize_matrix(size_b, size_b_to), geometry.transform_points(b_from_a, points_a))
    np.testing.assert_allclose(geometry.transform_points(rescaled, in_resized_a), in_resized_b, atol=1e-6)
    # There and back is the identity.
    back = geometry.rescale_homography(rescaled, size_a_to, size_a, size_b_to, size_b)
    np.testing.assert_allclose(back, b_from_a, rtol=1e-9, atol=1e-12)


def test_rescale_homography_of_identity_between_sizes_is_not_a_plain_scale():
    # Half-pixel aware: halving a 320-px-wide image maps x to (x + 0.5) / 2 - 0.5, not x / 2.
    rescaled = geometry.rescale_homography(np.eye(3), (320, 240), (160, 120))
    np.testing.assert_allclose(rescaled, np.eye(3), atol=1e-15)  # both images resized the same way
    a_to_small_b = geometry.rescale_homography(np.eye(3), (320, 240), (320, 240), (320, 240), (160, 120))
    np.testing.assert_allclose(a_to_small_b, [[0.5, 0, -0.25], [0, 0.5, -0.25], [0, 0, 1]], atol=1e-15)


@pytest.mark.parametrize(("size_to", "interpolation"), [((192, 144), cv2.INTER_LINEAR), ((64, 48), cv2.INTER_AREA), ((150, 60), cv2.INTER_LINEAR)])
def test_warp_then_resize_equals_resize_then_warp_with_rescaled_homography(size_to, interpolation):
    size = (96, 72)
    image_a = smooth_image(*size, seed=2, sigma=4.0)
    b_from_a = geometry.homography_from_offsets(random_offsets(3, *size, fraction=0.1), *size)
    warped_then_resized = cv2.resize(cv2.warpPerspective(image_a, b_from_a, size, flags=cv2.INTER_LINEAR), size_to, interpolation=interpolation)
    rescaled = geometry.rescale_homography(b_from_a, size, size_to)
    resized_then_warped = cv2.warpPerspective(cv2.resize(image_a, size_to, interpolation=interpolation), rescaled, size_to, flags=cv2.INTER_LINEAR)
    inside = cv2.warpPerspective(np.ones(size_to[::-1], np.float32), rescaled, size_to, flags=cv2.INTER_NEAREST)
    inside = interior(inside, 7)
    difference = np.abs(warped_then_resized - resized_then_warped)[inside]
    assert difference.mean() < 0.005 and difference.max() < 0.03
    # The same comparison with a naive x' = s x rescaling is visibly worse.
    sx, sy = size_to[0] / size[0], size_to[1] / size[1]
    naive = np.diag([sx, sy, 1.0]) @ b_from_a @ np.diag([1 / sx, 1 / sy, 1.0])
    naive_warp = cv2.warpPerspective(cv2.resize(image_a, size_to, interpolation=interpolation), naive, size_to, flags=cv2.INTER_LINEAR)
    assert np.abs(warped_then_resized - naive_warp)[inside].mean() > difference.mean()


# --------------------------------------------------------------------------------------- metrics


def test_mace_and_rmse_of_a_pure_translation():
    truth = np.eye(3)
    estimate = geometry.translation(3, 4)
    assert float(geometry.mace(estimate, truth, 320, 240)) == pytest.approx(5.0, abs=1e-12)
    assert float(geometry.corner_rmse(estimate, truth, 320, 240)) == pytest.approx(5.0, abs=1e-12)
    np.testing.assert_allclose(geometry.corner_errors(estimate, truth, 320, 240), [5.0] * 4, atol=1e-12)


def test_mace_and_rmse_differ_when_corner_errors_differ():
    # Only the top-right corner is off, by (6, 8): errors are (0, 10, 0, 0).
    offsets = np.zeros((4, 2))
    offsets[1] = (6.0, 8.0)
    estimate = geometry.homography_from_offsets(offsets, 100, 80)
    np.testing.assert_allclose(geometry.corner_errors(estimate, np.eye(3), 100, 80), [0, 10, 0, 0], atol=1e-9)
    assert float(geometry.mace(estimate, np.eye(3), 100, 80)) == pytest.approx(2.5, abs=1e-9)
    assert float(geometry.corner_rmse(estimate, np.eye(3), 100, 80)) == pytest.approx(5.0, abs=1e-9)


def test_mace_ignores_homography_scale_and_is_symmetric():
    truth = geometry.homography_from_offsets(random_offsets(8, 320, 240), 320, 240)
    estimate = truth @ geometry.translation(1.0, -2.0)
    assert float(geometry.mace(7.0 * estimate, truth, 320, 240)) == pytest.approx(float(geometry.mace(estimate, truth, 320, 240)))
    assert float(geometry.mace(estimate, truth, 320, 240)) == pytest.approx(float(geometry.mace(truth, estimate, 320, 240)))


def test_mace_is_batched():
    estimates = np.stack([geometry.translation(3, 4), geometry.translation(0, 1), np.eye(3)])
    np.testing.assert_allclose(geometry.mace(estimates, np.eye(3), 64, 64), [5.0, 1.0, 0.0], atol=1e-12)


# ------------------------------------------------------------------------------------ validation


def test_is_valid_homography_accepts_mild_and_rejects_broken():
    mild = geometry.homography_from_offsets(random_offsets(9, 320, 240, fraction=0.15), 320, 240)
    assert geometry.is_valid_homography(mild, 320, 240)
    assert geometry.is_valid_homography(np.eye(3), 320, 240)
    assert geometry.is_valid_homography(-2.0 * mild, 320, 240)  # a homography is defined up to scale, sign too

    assert not geometry.is_valid_homography(None, 320, 240)
    with_nan = mild.copy()
    with_nan[0, 1] = np.nan
    assert not geometry.is_valid_homography(with_nan, 320, 240)
    assert not geometry.is_valid_homography(np.full((3, 3), np.inf), 320, 240)
    assert not geometry.is_valid_homography(np.zeros((3, 3)), 320, 240)
    assert not geometry.is_valid_homography(np.array([[1.0, 2, 3], [2, 4, 6], [0, 0, 1]]), 320, 240)  # rank 2
    assert not geometry.is_valid_homography(np.eye(2), 320, 240)
    # A frame far from the reference of a large survey is no less valid than one beside it.
    assert geometry.is_valid_homography(geometry.translation(-159.5, -23076.7), 320, 240, max_scale=3.0)
    assert geometry.is_valid_homography(geometry.translation(1e6, 1e6) @ mild, 320, 240)
    assert not geometry.is_valid_homography(geometry.translation(1e6, 1e6) @ np.array([[1.0, 2, 3], [2, 4, 6], [0, 0, 1]]), 320, 240)

    # Folded: the top-right and bottom-right corners swapped places.
    corners = geometry.image_corners(320, 240)
    swapped = corners[[0, 2, 1, 3]] + [[0, 0], [5, 3], [-4, 2], [0, 0]]
    folded = cv2.getPerspectiveTransform(corners.astype(np.float32), swapped.astype(np.float32))
    assert not geometry.is_valid_homography(folded, 320, 240)
    # Mirrored (clockwise becomes anticlockwise): not a view of the same plane from the front.
    assert not geometry.is_valid_homography(np.diag([-1.0, 1.0, 1.0]) @ geometry.translation(-319, 0), 320, 240)
    # The horizon crosses the image: one corner maps through infinity.
    assert not geometry.is_valid_homography(np.array([[1.0, 0, 0], [0, 1, 0], [-1 / 200, 0, 1]]), 320, 240)
    # A 30x zoom is beyond max_scale (20) in both directions.
    assert not geometry.is_valid_homography(np.diag([30.0, 30.0, 1.0]), 320, 240)
    assert not geometry.is_valid_homography(np.diag([1 / 30, 1 / 30, 1.0]), 320, 240)
    assert geometry.is_valid_homography(np.diag([10.0, 10.0, 1.0]), 320, 240)


@pytest.mark.parametrize("horizontal", [True, False])
def test_mirror_matrix_is_cv2_flip_and_its_own_inverse(horizontal):
    image = np.arange(7 * 5, dtype=np.float32).reshape(5, 7)
    mirror = geometry.mirror_matrix(7, 5, horizontal)
    flipped = cv2.flip(image, 1 if horizontal else 0)
    for x, y in [(0, 0), (6, 0), (2, 3), (6, 4)]:
        xm, ym = geometry.transform_points(mirror, np.array([[x, y]], float))[0]
        assert flipped[int(round(ym)), int(round(xm))] == image[y, x]
    np.testing.assert_allclose(mirror @ mirror, np.eye(3))

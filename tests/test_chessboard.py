"""Chessboard calibration against views rendered under known intrinsics and distortion.

The board is scikit-image's bundled checkerboard (8 × 6 of its squares: 7 × 5 inner corners),
laid on a plane and seen through a known pinhole + distortion camera: every output pixel is
undistorted to a ray, the ray meets the board plane, and the texture is sampled there.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import skimage.data
import yaml

from vtolpose.config import load_config
from vtolpose.estimator.calibration.chessboard import Board, ChessboardError, calibrate_views, find_corners
from vtolpose.service.cli import main

K_TRUE = np.array([[520.0, 0.0, 322.0], [0.0, 515.0, 241.0], [0.0, 0.0, 1.0]])
DIST_TRUE = np.array([-0.28, 0.09, 0.0008, -0.0006, 0.0])
SIZE = (640, 480)
BOARD = Board(7, 5, 0.03)
PX_PER_SQUARE = 40


class BoardRenderer:
    def __init__(self) -> None:
        tex = skimage.data.checkerboard()[:150, :]  # 6 rows x 8 columns of 25 px squares
        tex = cv2.resize(tex, None, fx=PX_PER_SQUARE / 25, fy=PX_PER_SQUARE / 25, interpolation=cv2.INTER_NEAREST)
        self.texture = cv2.copyMakeBorder(tex, *[PX_PER_SQUARE] * 4, cv2.BORDER_CONSTANT, value=255)  # quiet zone
        u, v = np.meshgrid(np.arange(SIZE[0], dtype=float), np.arange(SIZE[1], dtype=float))
        pixels = np.column_stack([u.ravel(), v.ravel()]).reshape(-1, 1, 2)
        criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 40, 1e-10)
        normalised = cv2.undistortPoints(pixels, K_TRUE, DIST_TRUE, criteria=criteria).reshape(-1, 2)
        self.rays = np.column_stack([normalised, np.ones(len(normalised))])

    def render(self, rvec: np.ndarray, tvec: np.ndarray) -> np.ndarray:
        R, _ = cv2.Rodrigues(rvec)
        a = self.rays @ R  # rays in board axes
        b = R.T @ tvec
        scale = b[2] / a[:, 2]  # where each ray meets the board plane z = 0
        xb = scale[:, None] * a - b
        # Inner corner (0, 0) sits one square in from the board's edge, plus the quiet zone.
        mx = (xb[:, 0] / BOARD.square_m + 2.0) * PX_PER_SQUARE - 0.5
        my = (xb[:, 1] / BOARD.square_m + 2.0) * PX_PER_SQUARE - 0.5
        behind = scale <= 0
        mx[behind] = my[behind] = -1.0
        shape = (SIZE[1], SIZE[0])
        return cv2.remap(self.texture, mx.reshape(shape).astype(np.float32), my.reshape(shape).astype(np.float32),
                         cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=128)


def poses(n: int, seed: int, tilt: float = 0.6) -> list[tuple[np.ndarray, np.ndarray]]:
    rng = np.random.default_rng(seed)
    centre = np.array([3 * BOARD.square_m, 2 * BOARD.square_m, 0.0])
    out = []
    for _ in range(n):
        rvec = np.array([rng.uniform(-tilt, tilt), rng.uniform(-tilt, tilt), rng.uniform(-0.3, 0.3)])
        R, _ = cv2.Rodrigues(rvec)
        target = np.array([rng.uniform(-0.08, 0.08), rng.uniform(-0.05, 0.05), rng.uniform(0.28, 0.4)])
        out.append((rvec, target - R @ centre))
    return out


@pytest.fixture(scope="module")
def images() -> list[np.ndarray]:
    renderer = BoardRenderer()
    return [renderer.render(r, t) for r, t in poses(10, seed=1)]


@pytest.fixture(scope="module")
def views(images) -> list[tuple[str, np.ndarray]]:
    found = [(f"view{k:02d}", find_corners(img, BOARD)) for k, img in enumerate(images)]
    return [(name, c) for name, c in found if c is not None]


def test_intrinsics_within_1_percent_and_subpixel_error(views) -> None:
    assert len(views) >= 9
    cal = calibrate_views(views, BOARD, SIZE)
    for got, want in zip((cal.K[0, 0], cal.K[1, 1], cal.K[0, 2], cal.K[1, 2]), (520.0, 515.0, 322.0, 241.0)):
        assert got == pytest.approx(want, rel=0.01)
    assert cal.rms_px < 0.3
    assert np.all(cal.view_rms_px < 0.3)
    assert cal.distortion[0] == pytest.approx(DIST_TRUE[0], abs=0.03)
    assert cal.drop == []
    assert cal.camera().fx == cal.K[0, 0]


def test_a_view_with_a_displaced_corner_is_named_for_dropping(views) -> None:
    bad = [(name, c.copy()) for name, c in views]
    bad[3][1][10] += (4.0, -3.0)  # a mis-detected corner: 5 px off
    cal = calibrate_views(bad, BOARD, SIZE)
    assert cal.drop == [bad[3][0]]


def test_too_few_views_say_what_to_record(views) -> None:
    with pytest.raises(ChessboardError, match=r"found in 5 view\(s\); at least 8 are needed: record 10-20 views"):
        calibrate_views(views[:5], BOARD, SIZE)


def test_views_that_are_all_alike_are_refused() -> None:
    renderer = BoardRenderer()
    same = [(f"v{k}", find_corners(renderer.render(np.array([0.0, 0.0, 0.01 * k]), np.array([-0.09, -0.06, 0.33])), BOARD))
            for k in range(8)]
    with pytest.raises(ChessboardError, match=r"views are too alike"):
        calibrate_views(same, BOARD, SIZE)


def test_cli_writes_a_block_the_config_accepts(images, tmp_path, capsys) -> None:
    folder = tmp_path / "shots"
    folder.mkdir()
    for k, img in enumerate(images):
        cv2.imwrite(str(folder / f"shot{k:02d}.png"), img)
    cv2.imwrite(str(folder / "blank.png"), np.full((SIZE[1], SIZE[0]), 200, np.uint8))  # no board in it
    out = tmp_path / "camera.yaml"
    assert main(["calibrate", "camera", str(folder), "--board", "7x5", "--square", "0.03", "--out", str(out)]) == 0
    assert out.with_suffix(".png").read_bytes().startswith(b"\x89PNG")  # the reprojection figure
    printed = capsys.readouterr().out
    assert "board not found in 1 image(s): blank.png" in printed
    cfg = load_config(out)
    assert cfg["calibration.camera.fx"] == pytest.approx(520.0, rel=0.01)
    assert cfg["calibration.camera.width"] == 640
    assert "camera: {width: 640" in out.read_text()  # the dataset.yaml form, as a comment
    assert yaml.safe_load(out.read_text())["calibration"]["camera"]["rms_reprojection_px"] < 0.3


def test_cli_refuses_too_few_views_and_names_the_missing(images, tmp_path, capsys) -> None:
    for k in range(3):
        cv2.imwrite(str(tmp_path / f"shot{k}.png"), images[k])
    cv2.imwrite(str(tmp_path / "blank.png"), np.full((SIZE[1], SIZE[0]), 200, np.uint8))
    code = main(["calibrate", "camera", str(tmp_path), "--board", "7x5", "--square", "0.03",
                 "--out", str(tmp_path / "c.yaml"), "--no-plot"])
    assert code == 1
    err = capsys.readouterr().err
    assert "found in 3 view(s)" in err and "not found in 1 of 4 images: blank.png" in err
    assert not (tmp_path / "c.yaml").exists()

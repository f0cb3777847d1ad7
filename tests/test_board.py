"""Marker board: ring geometry, texture convention (checked by detecting the markers), printable image."""

import cv2
import numpy as np
import pytest
from PIL import Image

from argen.config import BoardConfig
from argen.errors import ArgenError
from argen.sim.board import Board, texture_uv

CONFIGS = [BoardConfig(), BoardConfig(markers_per_side=7, marker_size=0.045, marker_gap=0.015, margin=0.01)]


def _boxes(board):
    """(M, 2, 2) per marker [[xmin, xmax], [ymin, ymax]]."""
    c = board.marker_corners
    return np.stack([np.stack([c[..., 0].min(1), c[..., 0].max(1)], 1),
                     np.stack([c[..., 1].min(1), c[..., 1].max(1)], 1)], 1)


@pytest.mark.parametrize("cfg", CONFIGS)
def test_ring_geometry(cfg):
    b = Board.from_config(cfg)
    n, ms = cfg.markers_per_side, cfg.marker_size
    assert b.side == pytest.approx(2 * cfg.margin + n * ms + (n - 1) * cfg.marker_gap)
    M = 4 * (n - 1)
    assert b.marker_corners.shape == (M, 4, 3) and len(set(b.marker_ids.tolist())) == M
    c = b.marker_corners
    assert np.all(c[..., 2] == 0)
    # squares of marker_size in cv2.aruco order TL, TR, BR, BL seen from above (x right, y up)
    np.testing.assert_allclose(c[:, 1] - c[:, 0], np.tile([ms, 0, 0], (M, 1)), atol=1e-12)
    np.testing.assert_allclose(c[:, 3] - c[:, 0], np.tile([0, -ms, 0], (M, 1)), atol=1e-12)
    np.testing.assert_allclose(c[:, 2] - c[:, 0], np.tile([ms, -ms, 0], (M, 1)), atol=1e-12)
    # inside the ring band: within the outer margin, never reaching into the free square
    assert np.abs(c[..., :2]).max() <= b.side / 2 - cfg.margin + 1e-12
    box = _boxes(b)
    f = b.free_half_extent
    overlaps_free = (box[:, 0, 0] < f) & (box[:, 0, 1] > -f) & (box[:, 1, 0] < f) & (box[:, 1, 1] > -f)
    assert not overlaps_free.any()
    assert f > 0.15  # room for LineMOD objects on both configs
    # every marker touches the outer band of the ring (it is on an edge), and all are pairwise apart
    assert np.all(np.abs(c[..., :2]).max(axis=(1, 2)) == pytest.approx(b.side / 2 - cfg.margin))
    i, j = np.triu_indices(M, 1)
    sep_x = np.maximum(box[i, 0, 0] - box[j, 0, 1], box[j, 0, 0] - box[i, 0, 1])
    sep_y = np.maximum(box[i, 1, 0] - box[j, 1, 1], box[j, 1, 0] - box[i, 1, 1])
    assert np.maximum(sep_x, sep_y).min() == pytest.approx(cfg.marker_gap)
    # the cv2 board holds exactly these corners and ids
    np.testing.assert_allclose(np.asarray(b.cv_board.getObjPoints()), c, atol=1e-6)
    np.testing.assert_array_equal(np.asarray(b.cv_board.getIds()).ravel(), b.marker_ids)


def test_texture_convention_matches_detected_corners():
    """Detecting the markers in the flat texture finds every id at the documented pixel positions."""
    b = Board.from_config(CONFIGS[0])
    tex = b.texture(800)
    W = tex.shape[0]
    assert tex.shape == (W, W, 3) and tex.dtype == np.uint8 and W == round(b.side * 800)
    assert tex[W // 2, W // 2].tolist() == [255, 255, 255] and tex[0, 0].tolist() == [255, 255, 255]
    pad = 30
    img = cv2.copyMakeBorder(tex[..., 0], pad, pad, pad, pad, cv2.BORDER_CONSTANT, value=255)
    corners, ids, _ = b.detector.detectMarkers(img)
    ids = ids.ravel()
    assert sorted(ids.tolist()) == b.marker_ids.tolist()
    found = np.asarray(corners).reshape(-1, 4, 2) - pad
    expect = b.marker_corners[ids]
    ppm = W / b.side
    u = (expect[..., 0] + b.side / 2) * ppm - 0.5  # x = -side/2 + (u + 0.5) / ppm
    v = (b.side / 2 - expect[..., 1]) * ppm - 0.5  # y = side/2 - (v + 0.5) / ppm
    assert np.abs(found - np.stack([u, v], -1)).max() < 0.5
    # texture_uv (OpenGL, v up) addresses the same pixels
    uv = texture_uv(expect[..., :2].reshape(-1, 2), b.side).reshape(-1, 4, 2)
    assert uv.min() >= 0 and uv.max() <= 1
    np.testing.assert_allclose(uv[..., 0] * W - 0.5, u, atol=1e-9)
    np.testing.assert_allclose((1 - uv[..., 1]) * W - 0.5, v, atol=1e-9)
    np.testing.assert_allclose(texture_uv(np.array([[-b.side / 2, -b.side / 2], [b.side / 2, b.side / 2]]), b.side),
                               [[0, 0], [1, 1]])


def test_print_has_true_size_dpi_metadata_and_a_label_clear_of_markers(tmp_path):
    b = Board.from_config(CONFIGS[0])
    dpi = 150
    path = b.save_print(tmp_path / "board.png", dpi=dpi)
    im = Image.open(path)
    expect = b.side / 0.0254 * dpi
    assert abs(im.size[0] - expect) <= 1 and abs(im.size[1] - expect) <= 1
    # PNG stores whole pixels per metre, so the dpi read back is within half a pixel per metre
    assert im.info["dpi"] == pytest.approx((dpi, dpi), rel=0.5 * 0.0254 / dpi)
    assert im.size[0] / im.info["dpi"][0] * 0.0254 == pytest.approx(b.side, abs=0.0003)  # prints at true size
    img = np.asarray(im)
    plain = np.round(255 * (1 - b.raster(dpi / 0.0254))).astype(np.uint8)
    diff = np.argwhere(img != plain)
    assert len(diff) > 100  # the label is there ...
    ppm = img.shape[0] / b.side
    assert diff[:, 0].min() > img.shape[0] - b.cfg.margin * ppm  # ... only in the bottom margin
    marker_rows = np.argwhere((plain < 128).any(axis=1)).ravel()
    assert diff[:, 0].min() > marker_rows.max() + 1  # not touching the markers


def test_print_label_left_out_when_margin_too_small():
    b = Board.from_config(BoardConfig(margin=0.001))
    img = b.print_image(100)
    plain = np.round(255 * (1 - b.raster(100 / 0.0254))).astype(np.uint8)
    np.testing.assert_array_equal(img, plain)


@pytest.mark.parametrize("kw, words", [
    (dict(dictionary="DICT_9X9_7"), "dictionary"),
    (dict(dictionary="DICT_4X4_50", markers_per_side=14), "markers"),
    (dict(markers_per_side=2, marker_gap=0.004), "free"),
])
def test_bad_boards_are_user_errors(kw, words):
    with pytest.raises(ArgenError, match=words):
        Board.from_config(BoardConfig(**kw))

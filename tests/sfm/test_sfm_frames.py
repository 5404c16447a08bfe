"""Frame sampling: blur and near-duplicate rejection, enhancement, masks, video and folder input."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import cv2
import numpy as np
import pytest

from cadalign.errors import InputError
from cadalign.io import read_image, write_image
from cadalign.sfm.config import FrameConfig
from cadalign.sfm.frames import enhance, extract_frames, motion_between, select_frames, sharpness

W, H = 240, 180


def _texture(seed: int = 0, size: int = 600) -> np.ndarray:
    """A seeded RGB texture with detail at several scales (trackable corners everywhere)."""
    rng = np.random.default_rng(seed)
    img = np.zeros((size, size, 3), np.float32)
    for scale in (4, 16, 64):
        small = rng.random((size // scale, size // scale, 3)).astype(np.float32)
        img += cv2.resize(small, (size, size), interpolation=cv2.INTER_CUBIC)
    img = (img - img.min()) / (img.max() - img.min())
    return (img * 255).astype(np.uint8)


def _sequence() -> tuple[list[tuple[str, str, np.ndarray]], dict[str, str]]:
    """Crops panning right 10 px per frame; frame 3 is blurred, frame 6 repeats frame 5 (plus noise)."""
    tex = _texture()
    rng = np.random.default_rng(1)
    frames, expected = [], {}
    x = 0
    for k in range(10):
        if k != 6:
            x += 10
        img = tex[100 : 100 + H, x : x + W].copy()
        reason = ""
        if k == 3:
            img = cv2.GaussianBlur(img, (0, 0), 3.0)
            reason = "blurred"
        if k == 6:
            img = np.clip(img.astype(np.int16) + rng.integers(-2, 3, img.shape), 0, 255).astype(np.uint8)
            reason = "near-duplicate"
        frames.append((f"{k:06d}.png", str(k), img))
        expected[f"{k:06d}.png"] = reason
    return frames, expected


def test_sharpness_orders_blur():
    img = cv2.cvtColor(_texture()[:H, :W], cv2.COLOR_RGB2GRAY)
    assert sharpness(img) > 3 * sharpness(cv2.GaussianBlur(img, (0, 0), 2.0))


def test_motion_between_measures_a_shift():
    gray = cv2.cvtColor(_texture()[:, :, :], cv2.COLOR_RGB2GRAY)
    a, b = gray[100 : 100 + H, 50 : 50 + W], gray[100 : 100 + H, 62 : 62 + W]
    assert motion_between(a, b) == pytest.approx(12 / np.hypot(W, H), rel=0.1)
    assert motion_between(a, a) < 1e-3


def test_select_frames_rejects_blur_and_duplicates():
    frames, expected = _sequence()
    decisions = [d for d, _ in select_frames(frames, FrameConfig())]
    assert {d.name: d.reason for d in decisions} == expected
    assert [d.kept for d in decisions] == [not r for r in expected.values()]
    assert decisions[0].motion == -1.0 and decisions[1].motion > 0


def _pan(soft: dict[int, np.ndarray], n: int = 10) -> list[tuple[str, str, np.ndarray]]:
    """Crops panning right 10 px per frame; frame k is filtered with the kernel ``soft[k]`` when given."""
    tex = _texture()
    out = []
    for k in range(n):
        img = tex[100 : 100 + H, 10 * (k + 1) : 10 * (k + 1) + W].copy()
        if k in soft:
            img = cv2.filter2D(img, -1, soft[k])
        out.append((f"{k:06d}.png", str(k), img))
    return out


def _gauss(sigma: float) -> np.ndarray:
    g = cv2.getGaussianKernel(int(6 * sigma) | 1, sigma)
    return (g @ g.T).astype(np.float32)


def _motion(length: int) -> np.ndarray:
    k = np.zeros((length, length), np.float32)
    k[length // 2, :] = 1 / length
    return k


def test_softer_frames_that_still_match_are_kept():
    # sigma 1.5 px: under a third of the neighbours' sharpness (below blur_ratio 0.35), yet most matches survive
    frames = _pan({3: _gauss(1.5), 7: _gauss(1.5)})
    gray = [cv2.cvtColor(f[2], cv2.COLOR_RGB2GRAY) for f in frames]
    assert sharpness(gray[3]) < 0.35 * sharpness(gray[2])
    decisions = [d for d, _ in select_frames(frames, FrameConfig())]
    assert all(d.kept for d in decisions), [(d.name, d.reason) for d in decisions]
    assert decisions[3].matches > 0 and decisions[7].matches > 0
    assert decisions[2].matches == -1  # sharp frames are not match-checked
    # sharpness alone (the check off) drops them: the match check is what keeps them
    alone = [d for d, _ in select_frames(frames, FrameConfig(blur_keep_matches=0.0))]
    assert [d.name for d in alone if d.reason == "blurred"] == ["000003.png", "000007.png"]


@pytest.mark.parametrize("kernel", [_gauss(3.0), _motion(15), _motion(25)], ids=["gauss3", "motion15", "motion25"])
def test_a_truly_blurred_frame_among_sharp_ones_is_dropped(kernel: np.ndarray):
    frames = _pan({5: kernel})
    decisions = [d for d, _ in select_frames(frames, FrameConfig())]
    assert [d.name for d in decisions if not d.kept] == ["000005.png"]
    assert decisions[5].reason == "blurred" and 0 <= decisions[5].matches


def test_the_match_check_is_relative_to_the_sequence():
    # the same soft frame in a sequence that is soft everywhere (murky water) is not judged against sharp frames
    frames = _pan({k: _gauss(1.5) for k in range(10)} | {5: _gauss(3.0)})
    decisions = [d for d, _ in select_frames(frames, FrameConfig())]
    assert [d.name for d in decisions if not d.kept] == ["000005.png"]


def test_select_frames_checks_off_keeps_everything():
    frames, _ = _sequence()
    cfg = FrameConfig(blur_ratio=0.0, min_motion=0.0)
    assert all(d.kept for d, _ in select_frames(frames, cfg))


def test_select_frames_motion_sampling_and_max_frames():
    frames, _ = _sequence()
    cfg = FrameConfig(sampling="motion", keyframe_motion=25 / np.hypot(W, H), blur_ratio=0.0)
    kept = [d.name for d, _ in select_frames(frames, cfg) if d.kept]
    assert kept[0] == "000000.png" and 3 <= len(kept) <= 5  # a keyframe every ~3 frames of 10 px
    capped = [d for d, _ in select_frames(frames, FrameConfig(max_frames=2, blur_ratio=0.0, min_motion=0.0))]
    assert sum(d.kept for d in capped) == 2 and capped[-1].reason == "max_frames"


def test_enhance_none_is_identity_and_clahe_raises_contrast():
    img = (_texture()[:H, :W] // 4 + 40).astype(np.uint8)  # dim, low contrast
    assert enhance(img, FrameConfig(enhance="none")) is img
    out = enhance(img, FrameConfig(enhance="clahe"))
    assert out.shape == img.shape and out.dtype == np.uint8
    assert out.std() > 1.5 * img.std()
    wb = enhance(np.dstack([img[..., 0] // 2, img[..., 1], img[..., 2]]), FrameConfig(enhance="clahe_wb"))
    assert wb.shape == img.shape


def _write_folder(folder: Path, frames: list[tuple[str, str, np.ndarray]]) -> None:
    for name, _, img in frames:
        write_image(folder / name, img)


def test_extract_frames_from_folder_writes_kept_frames_and_masks(tmp_path):
    frames, expected = _sequence()
    _write_folder(tmp_path / "in", frames)
    mask = np.full((H, W), 255, np.uint8)
    mask[-20:] = 0  # ROV hardware at the bottom
    write_image(tmp_path / "mask.png", mask)
    cfg = FrameConfig(enhance="none", mask=tmp_path / "mask.png", mask_rects=((0, 0, 30, 10),))
    decisions = extract_frames(tmp_path / "in", cfg, tmp_path / "images", tmp_path / "masks")
    kept = sorted(n for n, r in expected.items() if not r)
    assert sorted(p.name for p in (tmp_path / "images").iterdir()) == kept
    assert np.array_equal(read_image(tmp_path / "images" / kept[0]), frames[0][2])  # copied losslessly
    m = read_image(tmp_path / "masks" / f"{kept[0]}.png", unchanged=True)
    assert m.shape == (H, W) and m[-1].max() == 0 and m[0, :30].max() == 0 and m[50, 100] == 255
    assert len(decisions) == 10


def test_extract_frames_from_video(tmp_path):
    frames, _ = _sequence()
    path = tmp_path / "dive.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10.0, (W, H))
    assert writer.isOpened()
    for _, _, img in frames:
        writer.write(np.ascontiguousarray(img[..., ::-1]))
    writer.release()
    cfg = FrameConfig(sampling="fps", fps=5.0, enhance="clahe", blur_ratio=0.0, min_motion=0.0)
    decisions = extract_frames(path, cfg, tmp_path / "images", tmp_path / "masks")
    assert [d.name for d in decisions] == ["000000.png", "000002.png", "000004.png", "000006.png", "000008.png"]
    assert (tmp_path / "images" / "000004.png").is_file() and not (tmp_path / "masks").exists()


def test_extract_frames_errors_name_the_input(tmp_path):
    with pytest.raises(InputError, match="not found"):
        extract_frames(tmp_path / "nope", FrameConfig(), tmp_path / "i", tmp_path / "m")
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match="no images"):
        extract_frames(tmp_path / "empty", FrameConfig(), tmp_path / "i", tmp_path / "m")
    frames, _ = _sequence()
    _write_folder(tmp_path / "same", [frames[0], (frames[1][0], "", frames[0][2])])
    with pytest.raises(InputError, match="only 1 of 2 frames are usable"):
        extract_frames(tmp_path / "same", FrameConfig(), tmp_path / "i", tmp_path / "m")
    _write_folder(tmp_path / "in", frames[:3])
    write_image(tmp_path / "small_mask.png", np.ones((10, 10), np.uint8))
    cfg = dataclasses.replace(FrameConfig(), mask=tmp_path / "small_mask.png")
    with pytest.raises(InputError, match="resize the mask"):
        extract_frames(tmp_path / "in", cfg, tmp_path / "i2", tmp_path / "m2")

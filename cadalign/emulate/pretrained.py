"""The user's pretrained depth and segmentation checkpoints on disk, loaded through ``transformers`` (GenLaM).

A checkpoint is a folder written by ``save_pretrained`` (``config.json`` + weights, optionally
``preprocessor_config.json``). Loading never touches the network (``local_files_only=True``). Supported:

- depth: ``depth_anything`` (Depth Anything V1/V2; ``depth_estimation_type`` ``metric`` gives metres,
  ``relative`` gives affine-invariant *disparity*) and ``dpt`` (DPT / MiDaS: relative disparity);
- classes: ``segformer`` (e.g. the ADE20k checkpoints; class names from the config's ``id2label``).

Neither depth architecture predicts a point map or rays, so the focal length is not observable from them
(:mod:`cadalign.emulate.photo` takes it from EXIF, ``--hfov``, ``--calib`` or an ``.npz`` point map).

Preprocessing is ours, not the checkpoint's processor class: the photo is resized so its long side is
``PretrainedConfig.long_side_px`` (rounded to the model's patch multiple) and normalised with the
``image_mean``/``image_std`` of ``preprocessor_config.json`` (ImageNet's when absent); a plain-ViT DPT gets a
square input (its tokens are reshaped to a square grid), as its own processor does. The output is resized
back to the photo with bilinear interpolation.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import cv2
import numpy as np

from cadalign.config import bounded
from cadalign.errors import InputError

log = logging.getLogger(__name__)
DEPTH_ARCHS = ("depth_anything", "dpt")
"""``model_type`` values of ``config.json`` accepted as depth models."""
SEG_ARCHS = ("segformer",)
"""``model_type`` values of ``config.json`` accepted as segmentation models."""
PANE_WORDS = ("windowpane", "window", "glass", "pane", "screen")
"""Class names (words of ``id2label``) treated as planar panes (ADE20k: 'windowpane, window', 'glass')."""
_IMAGENET = ((0.485, 0.456, 0.406), (0.229, 0.224, 0.225))


@dataclass(frozen=True)
class PretrainedConfig:
    long_side_px: int = bounded(518, ge=14)
    """Long side of the network input, pixels (518 = Depth Anything's training size; rounded to the patch)."""
    device: str = "cpu"
    """Torch device."""


@dataclass(frozen=True)
class DepthOutput:
    """One depth prediction at the photo's size.

    Attributes:
        value: (H, W) float64: metres when ``kind == 'metric'``, else relative disparity (larger = nearer,
            known up to scale and shift).
        kind: ``metric`` or ``disparity``.
    """

    value: np.ndarray
    kind: Literal["metric", "disparity"]


@dataclass(frozen=True)
class SegModel:
    """A loaded segmentation checkpoint: ``predict(rgb) -> (C, H, W)`` probabilities and its class names."""

    predict: Callable[[np.ndarray], np.ndarray]
    class_names: tuple[str, ...]

    def pane_classes(self) -> tuple[int, ...]:
        """Ids whose name holds a word of :data:`PANE_WORDS` (e.g. ADE20k 'windowpane, window' and 'glass')."""
        words = [{w.strip() for w in n.lower().replace(",", " ").split()} for n in self.class_names]
        return tuple(i for i, ws in enumerate(words) if ws & set(PANE_WORDS))


def _model_type(path: Path, supported: tuple[str, ...], what: str) -> str:
    path = Path(path)
    cfg_file = path / "config.json"
    if not cfg_file.is_file():
        raise InputError(f"{what} checkpoint {path}: no config.json there; give a folder written by "
                         f"transformers' save_pretrained (supported: {', '.join(supported)}), downloaded beforehand")
    try:
        model_type = str(json.loads(cfg_file.read_text()).get("model_type", ""))
    except (OSError, ValueError) as exc:
        raise InputError(f"{cfg_file}: not readable JSON: {exc}") from exc
    if model_type not in supported:
        raise InputError(f"{what} checkpoint {path} is a {model_type or 'model without model_type'!r}; supported "
                         f"architectures: {', '.join(supported)}")
    return model_type


def _load(cls_name: str, path: Path, device: str):
    # transformers is an optional dependency (the `genlam` extra): only photo sources need it
    try:
        import transformers  # lazy: optional dependency (transformers)
    except ImportError as exc:
        raise InputError("pretrained checkpoints need the 'transformers' package: pip install 'cadalign[genlam]'") \
            from exc
    cls = getattr(transformers, cls_name)
    try:
        model = cls.from_pretrained(str(path), local_files_only=True)
    except (OSError, ValueError) as exc:
        raise InputError(f"could not load {path} as {cls_name} from local files: {exc}") from exc
    return model.to(device).eval()


def _norm_stats(path: Path) -> tuple[np.ndarray, np.ndarray]:
    p = Path(path) / "preprocessor_config.json"
    mean, std = _IMAGENET
    if p.is_file():
        d = json.loads(p.read_text())
        mean, std = d.get("image_mean", mean), d.get("image_std", std)
    return np.asarray(mean, np.float32), np.asarray(std, np.float32)


def _forward_size(H: int, W: int, long_side: int, multiple: int) -> tuple[int, int]:
    s = long_side / max(H, W)
    return (max(multiple, int(round(H * s / multiple)) * multiple),
            max(multiple, int(round(W * s / multiple)) * multiple))


def _pixels(rgb: np.ndarray, size: tuple[int, int], mean: np.ndarray, std: np.ndarray, device: str):
    import torch  # lazy: heavy dependency (torch)

    rgb = np.asarray(rgb)
    if rgb.ndim != 3 or rgb.shape[2] < 3:
        raise InputError(f"photo must be (H, W, 3) RGB, got {rgb.shape}")
    x = cv2.resize(rgb[..., :3], (size[1], size[0]), interpolation=cv2.INTER_CUBIC).astype(np.float32) / 255.0
    x = (x - mean) / std
    return torch.from_numpy(x.transpose(2, 0, 1)[None].copy()).to(device)


def _to_photo(t, H: int, W: int) -> np.ndarray:
    """(1, [C,] h, w) tensor -> ([C,] H, W) float64 numpy, bilinear."""
    import torch.nn.functional as F  # lazy: heavy dependency (torch)

    x = t if t.ndim == 4 else t[:, None]
    x = F.interpolate(x.float(), size=(H, W), mode="bilinear", align_corners=False)[0]
    out = x.detach().cpu().numpy().astype(np.float64)
    return out if t.ndim == 4 else out[0]


def load_depth_model(path: Path, cfg: PretrainedConfig = PretrainedConfig()) -> Callable[[np.ndarray], DepthOutput]:
    """A depth checkpoint folder -> ``predict(rgb (H, W, 3) uint8) -> DepthOutput`` (see the module docstring).

    Raises:
        InputError: no ``config.json``, an unsupported ``model_type`` (the message lists :data:`DEPTH_ARCHS`),
            weights that do not load, or ``transformers`` not installed.
    """
    import torch  # lazy: heavy dependency (torch)

    arch = _model_type(path, DEPTH_ARCHS, "depth")
    cls_name = "DepthAnythingForDepthEstimation" if arch == "depth_anything" else "DPTForDepthEstimation"
    model = _load(cls_name, path, cfg.device)
    mc = model.config
    patch = int(getattr(mc.backbone_config, "patch_size", 14)) if arch == "depth_anything" else \
        int(np.atleast_1d(getattr(mc, "patch_size", 16))[0])
    kind: Literal["metric", "disparity"] = (
        "metric" if getattr(mc, "depth_estimation_type", "relative") == "metric" else "disparity")
    # a plain-ViT DPT (no backbone_config, e.g. dpt-large) reshapes its tokens to a square grid: square input
    square = arch == "dpt" and getattr(mc, "backbone_config", None) is None
    mean, std = _norm_stats(path)
    log.info("depth checkpoint %s: %s, %s output, patch %d", path, arch, kind, patch)

    def predict(rgb: np.ndarray) -> DepthOutput:
        H, W = np.shape(rgb)[:2]
        size = _forward_size(H, W, cfg.long_side_px, patch)
        size = (max(size), max(size)) if square else size
        with torch.inference_mode():
            out = model(pixel_values=_pixels(rgb, size, mean, std, cfg.device)).predicted_depth
        return DepthOutput(_to_photo(out, H, W), kind)

    return predict


def load_seg_model(path: Path, cfg: PretrainedConfig = PretrainedConfig()) -> SegModel:
    """A segmentation checkpoint folder -> :class:`SegModel` (class names from ``id2label``).

    Raises:
        InputError: as :func:`load_depth_model`, with :data:`SEG_ARCHS`.
    """
    import torch  # lazy: heavy dependency (torch)

    _model_type(path, SEG_ARCHS, "segmentation")
    model = _load("SegformerForSemanticSegmentation", path, cfg.device)
    n = int(model.config.num_labels)
    id2label = {int(k): str(v) for k, v in (model.config.id2label or {}).items()}
    names = tuple(id2label.get(i, f"class {i}") for i in range(n))
    mean, std = _norm_stats(path)

    def predict(rgb: np.ndarray) -> np.ndarray:
        H, W = np.shape(rgb)[:2]
        with torch.inference_mode():
            logits = model(pixel_values=_pixels(rgb, _forward_size(H, W, cfg.long_side_px, 32), mean, std,
                                                cfg.device)).logits
        return _to_photo(logits.softmax(1), H, W)

    return SegModel(predict, names)

"""Atomic file writes and the stage manifest (resolved config + version beside outputs).

Every long stage writes through these helpers so that an interrupted run never
leaves a half-written file under its final name: data goes to a temporary file
in the same directory and is moved into place with ``os.replace``.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import shutil
import signal
import tempfile
from collections.abc import Collection, Iterator
from pathlib import Path
from typing import Any

import numpy as np

from cadalign._version import __version__
from cadalign.config import config_differences, config_fingerprint_dict, to_dict
from cadalign.errors import ConfigError, InputError

MANIFEST_NAME = "cadalign_stage.json"


@contextlib.contextmanager
def atomic_path(path: Path) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; move it into place on success."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp" + path.suffix, dir=path.parent)
    os.close(fd)
    try:
        yield Path(tmp)
        os.replace(tmp, path)
    finally:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)


def link_or_copy(src: Path, dst: Path) -> None:
    """Hard-link ``src`` to ``dst`` (replacing it), or copy where links are not possible."""
    dst.parent.mkdir(parents=True, exist_ok=True)
    if dst.exists():
        dst.unlink()
    try:
        os.link(src, dst)
    except OSError:
        shutil.copyfile(src, dst)


def write_bytes(path: Path, data: bytes) -> Path:
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)
    return Path(path)


def write_text(path: Path, text: str) -> Path:
    return write_bytes(path, text.encode("utf-8"))


def write_json(path: Path, obj: Any, *, indent: int | None = 2) -> Path:
    return write_text(path, json.dumps(obj, indent=indent, default=_json_default) + "\n")


def _json_default(obj: Any) -> Any:
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, (np.floating, np.integer, np.bool_)):
        return obj.item()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"not JSON serialisable: {type(obj).__name__}")


def read_json(path: Path) -> Any:
    path = Path(path)
    if not path.is_file():
        raise InputError(f"missing file: {path}")
    try:
        return json.loads(path.read_bytes().decode("utf-8"))
    except (ValueError, RecursionError) as exc:  # JSONDecodeError, UnicodeDecodeError, absurd nesting
        reason = f"{type(exc).__name__}: {exc}" if not isinstance(exc, json.JSONDecodeError) else str(exc)
        raise InputError(f"{path} is not valid JSON ({reason:.200}); delete it and re-run the stage "
                         "that wrote it") from exc


def read_jsonl(path: Path) -> list[Any]:
    """The records of a JSON-lines file (``track.jsonl``, ``poses.jsonl``), one per non-empty line."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"missing file: {path}")
    out = []
    for i, line in enumerate(path.read_text(encoding="utf-8").splitlines(), start=1):
        if not line.strip():
            continue
        try:
            out.append(json.loads(line))
        except ValueError as exc:
            raise InputError(f"{path}, line {i} is not valid JSON ({exc}); delete the file and re-run the stage "
                             "that wrote it (a run cut short leaves a partial last line)") from exc
    return out


def write_image(path: Path, image: np.ndarray, *, atomic: bool = True) -> Path:
    """Write an image (uint8/uint16; RGB order for 3 channels); format from the suffix.

    ``atomic=False`` skips the temp-file + rename, for callers that mark completion with a later
    atomic file of their own (a rename costs ~2 ms on some file systems; a frame has dozens of masks).
    """
    import cv2  # lazy: heavy dependency (cv2); keeps `cadalign --help` light

    img = image
    if img.ndim == 3 and img.shape[2] == 3:
        img = img[..., ::-1]
    ok, buf = cv2.imencode(Path(path).suffix, np.ascontiguousarray(img))
    if not ok:
        raise InputError(f"could not encode image for {path}")
    if not atomic:
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        Path(path).write_bytes(buf.tobytes())
        return Path(path)
    return write_bytes(path, buf.tobytes())


def read_image(path: Path, *, unchanged: bool = False) -> np.ndarray:
    """Read an image as RGB uint8 (or unchanged depth, e.g. uint16), naming the file on failure."""
    import cv2  # lazy: heavy dependency (cv2); keeps `cadalign --help` light

    path = Path(path)
    if not path.is_file():
        raise InputError(f"image not found: {path}")
    flag = cv2.IMREAD_UNCHANGED if unchanged else cv2.IMREAD_COLOR
    img = cv2.imread(str(path), flag)
    if img is None:
        raise InputError(f"could not decode image {path}: the file is corrupt or not an image; replace or remove it")
    if img.ndim == 3 and img.shape[2] >= 3:
        img = img[..., 2::-1] if img.shape[2] == 3 else img[..., [2, 1, 0, 3]]
    return np.ascontiguousarray(img)


def fingerprint(obj: Any) -> str:
    """A stable short hash of a JSON-serialisable object (configs, input lists)."""
    blob = json.dumps(obj, sort_keys=True, default=_json_default).encode()
    return hashlib.sha256(blob).hexdigest()[:16]


def prepare_stage_dir(out_dir: Path, stage: str, config: Any, *, overwrite: bool = False,
                      ignore: Collection[str] = ()) -> bool:
    """Claim ``out_dir`` for a stage run with ``config``.

    ``config`` is a config dataclass or a mapping that may hold config dataclasses (e.g.
    ``{"sfm": cfg, "source": ...}``); it is stored in full (:func:`cadalign.config.to_dict`), and compared
    through :func:`cadalign.config.config_fingerprint_dict`: a field at its default does not count, so a run
    made before a defaulted field existed is still the same config. Pass the dataclasses themselves, not their
    ``to_dict`` form, to get that (a plain dict has no defaults to compare with).

    Returns True when outputs of an identical config already exist there (the
    caller may reuse finished work). A directory made with a *different*
    config is refused unless ``overwrite`` is set, so results never silently
    mix two configurations. ``ignore`` names dotted key paths of ``config`` that a re-run may change
    (``config.loop.steps`` of a training run that may be extended): stored, but neither fingerprinted nor
    compared.

    Raises:
        ConfigError: the directory holds results of another config or stage.
    """
    out_dir = Path(out_dir)
    manifest_path = out_dir / MANIFEST_NAME
    record = {"stage": stage, "config": to_dict(config), "version": __version__,
              "fingerprint": fingerprint(_without(config_fingerprint_dict(config), ignore))}
    if manifest_path.exists() and not overwrite:
        old = read_json(manifest_path)
        differs = [] if old.get("fingerprint") == record["fingerprint"] else [
            k for k in config_differences(old.get("config"), config) if k not in ignore]
        if old.get("stage") != stage or differs:
            keys = f", differs in: {', '.join(differs[:8])}{' ...' if len(differs) > 8 else ''}" if differs else ""
            raise ConfigError(
                f"{out_dir} holds '{old.get('stage')}' results made with another config "
                f"(fingerprint {old.get('fingerprint')} vs {record['fingerprint']}{keys}); "
                "choose another output directory or pass --overwrite"
            )
        return True
    out_dir.mkdir(parents=True, exist_ok=True)
    write_json(manifest_path, record)
    return False


def _without(view: Any, keys: Collection[str]) -> Any:
    """``view`` (nested dicts) without the dotted key paths ``keys``."""
    if not keys or not isinstance(view, dict):
        return view
    out = {}
    for k, v in view.items():
        if k in keys:
            continue
        inner = {key.split(".", 1)[1] for key in keys if "." in key and key.split(".", 1)[0] == k}
        out[k] = _without(v, inner)
    return out


@contextlib.contextmanager
def stop_on_signals() -> Iterator[dict[str, bool]]:
    """Turn SIGINT/SIGTERM into a flag a long run checks between its steps, to stop there with its work kept
    (``flag["stop"]``; main thread only, elsewhere Ctrl-C stays a KeyboardInterrupt)."""
    flag = {"stop": False}

    def handler(signum: int, frame: Any) -> None:
        flag["stop"] = True

    old: dict[int, Any] = {}
    try:
        for sig in (signal.SIGINT, signal.SIGTERM):
            old[sig] = signal.signal(sig, handler)
    except ValueError:  # not the main thread: rely on KeyboardInterrupt
        pass
    try:
        yield flag
    finally:
        for sig, h in old.items():
            signal.signal(sig, h)

"""Read the mesh parts of a Gazebo SDF model (e.g. UUV Simulator's ``rov_bop_panel``).

Only what is needed to place CAD parts is read: each ``<link>``'s ``<pose>``,
its ``<visual>`` elements with a ``<mesh>`` (``<uri>``, ``<scale>``) and their
``<pose>``. Poses are ``x y z roll pitch yaw`` (metres, radians) with SDF's
convention ``R = Rz(yaw) @ Ry(pitch) @ Rx(roll)`` (extrinsic x-y-z). Link poses
are in the model frame and visual poses in the link frame (SDF <= 1.6 default;
``relative_to``/``frame`` attributes are refused rather than misread).
"""

from __future__ import annotations

import logging
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

from cadalign.cad.load import load_cad
from cadalign.cad.model import CadModel
from cadalign.errors import InputError
from cadalign.types import Rigid3

logger = logging.getLogger(__name__)


def rpy_to_matrix(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """SDF/URDF Euler angles (radians) to a (3, 3) rotation ``Rz(yaw) @ Ry(pitch) @ Rx(roll)``."""
    cr, sr, cp, sp, cy, sy = np.cos(roll), np.sin(roll), np.cos(pitch), np.sin(pitch), np.cos(yaw), np.sin(yaw)
    Rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    Ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    Rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    return Rz @ Ry @ Rx


def parse_pose(elem: ET.Element | None, where: str) -> Rigid3:
    """An SDF ``<pose>x y z roll pitch yaw</pose>`` as a :class:`Rigid3` (identity when absent)."""
    if elem is None or not (elem.text or "").strip():
        return Rigid3.identity()
    for attr in ("relative_to", "frame"):
        if elem.get(attr):
            raise InputError(f"{where}: <pose {attr}='{elem.get(attr)}'> is not supported; only poses relative "
                             "to the parent element are")
    try:
        vals = [float(x) for x in elem.text.split()]
    except ValueError as exc:
        raise InputError(f"{where}: <pose> must be 6 numbers 'x y z roll pitch yaw', got '{elem.text}'") from exc
    if len(vals) != 6:
        raise InputError(f"{where}: <pose> must be 6 numbers 'x y z roll pitch yaw', got {len(vals)}")
    return Rigid3(rpy_to_matrix(*vals[3:]), vals[:3])


def resolve_model_uri(uri: str, sdf_path: Path) -> Path:
    """Resolve a mesh ``<uri>``: ``model://NAME/rest`` -> ``<sdf dir>/../NAME/rest``; ``file://`` and
    plain paths are absolute or relative to the SDF's folder."""
    if uri.startswith("model://"):
        return sdf_path.parent.parent / uri[len("model://") :]
    if uri.startswith("file://"):
        uri = uri[len("file://") :]
    p = Path(uri)
    return p if p.is_absolute() else sdf_path.parent / p


def _read_sdf_model(sdf_path: Path) -> ET.Element:
    if not sdf_path.is_file():
        raise InputError(f"SDF file not found: '{sdf_path}'; check the path")
    try:
        root = ET.parse(sdf_path).getroot()
    except ET.ParseError as exc:
        raise InputError(f"cannot parse SDF '{sdf_path}': {exc}; check that it is valid XML") from exc
    model = root if root.tag == "model" else root.find("model")
    if model is None:
        raise InputError(f"SDF '{sdf_path}' has no <model> element at its top level")
    if model.find("include") is not None or model.find("model") is not None:
        logger.warning("SDF '%s': nested <model>/<include> elements are ignored", sdf_path)
    return model


def _mesh_visuals(link: ET.Element) -> list[tuple[str, ET.Element, ET.Element | None]]:
    out = []
    for vis in link.findall("visual"):
        mesh = vis.find("geometry/mesh")
        if mesh is None:
            logger.debug("SDF link %r: visual %r has no mesh; skipped", link.get("name"), vis.get("name"))
            continue
        out.append((vis.get("name", ""), mesh, vis.find("pose")))
    return out


def _parse_scale(mesh: ET.Element, where: str) -> tuple[float, float, float]:
    text = (mesh.findtext("scale") or "1 1 1").split()
    try:
        s = tuple(float(x) for x in text)
    except ValueError as exc:
        raise InputError(f"{where}: <scale> must be 3 numbers, got '{' '.join(text)}'") from exc
    if len(s) != 3:
        raise InputError(f"{where}: <scale> must be 3 numbers, got {len(s)}")
    return s  # type: ignore[return-value]


def load_sdf_model(
    sdf_path: str | Path, *, unit: str | None = "m", clean: bool = True, skip_missing: bool = False
) -> list[tuple[str, CadModel, Rigid3]]:
    """Load every mesh visual of an SDF model with its pose in the model frame.

    Args:
        sdf_path: the ``model.sdf`` file.
        unit: unit of the meshes (Gazebo meshes are metres); ``None`` detects it.
        clean: clean each mesh (see :func:`~cadalign.cad.load.load_cad`).
        skip_missing: log a warning and skip visuals whose mesh file is missing instead of raising.

    Returns:
        ``(name, model, T_model_from_part)`` per mesh visual, in file order. ``name`` is the
        link name (``link/visual`` when a link has several mesh visuals). ``<scale>`` is
        applied to the model's vertices. Identical (file, scale) pairs share one model.

    Raises:
        InputError: missing or malformed SDF, unsupported pose frames, or a missing mesh.
    """
    sdf_path = Path(sdf_path)
    model_el = _read_sdf_model(sdf_path)
    logger.debug("SDF '%s': model pose in world %s (not applied)", sdf_path.name, model_el.findtext("pose"))
    cache: dict[tuple[Path, tuple[float, float, float]], CadModel] = {}
    out: list[tuple[str, CadModel, Rigid3]] = []
    for link in model_el.findall("link"):
        lname = link.get("name", "")
        T_model_link = parse_pose(link.find("pose"), f"{sdf_path} link '{lname}'")
        visuals = _mesh_visuals(link)
        for vname, mesh, pose in visuals:
            where = f"{sdf_path} link '{lname}' visual '{vname}'"
            uri = (mesh.findtext("uri") or "").strip()
            path = resolve_model_uri(uri, sdf_path)
            if not path.is_file():
                msg = f"{where}: mesh '{uri}' not found at '{path}'"
                if skip_missing:
                    logger.warning("%s; skipped", msg)
                    continue
                raise InputError(msg + "; put the mesh there or pass skip_missing=True")
            scale = _parse_scale(mesh, where)
            key = (path.resolve(), scale)
            if key not in cache:
                part = load_cad(path, unit, clean=clean)
                cache[key] = part if scale == (1.0, 1.0, 1.0) else part.scaled(scale)
            name = lname if len(visuals) == 1 else f"{lname}/{vname}"
            out.append((name, cache[key], T_model_link @ parse_pose(pose, where)))
    return out

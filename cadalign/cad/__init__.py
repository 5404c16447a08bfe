"""CAD models: loading (units, parts, colours), cleaning, symmetries, SDF models and BOP export.

Everything inside cadalign is in metres; :func:`load_cad` converts on the way
in (recording the file's unit) and :mod:`~cadalign.cad.models_info` converts
to BOP's millimetres on the way out.

Example:
    >>> model = load_cad("Valve.dae")  # doctest: +SKIP
    >>> check_unit(model, expected_size_m=(0.05, 2.0))  # doctest: +SKIP
"""

from cadalign.cad.clean import CleanReport, clean_mesh, clean_model, edge_topology
from cadalign.cad.load import SUPPORTED_EXTENSIONS, CadParts, load_cad, read_cad_parts
from cadalign.cad.model import CadModel, max_pairwise_distance
from cadalign.cad.models_info import models_info_entry, write_model_ply_mm, write_models_info
from cadalign.cad.sdf import load_sdf_model, parse_pose, rpy_to_matrix
from cadalign.cad.symmetry import SYMMETRY_NAMES, Symmetry
from cadalign.cad.units import PLAUSIBLE_SIZE_M, UNIT_TO_M, check_unit, detect_unit

__all__ = [
    "PLAUSIBLE_SIZE_M",
    "SUPPORTED_EXTENSIONS",
    "SYMMETRY_NAMES",
    "UNIT_TO_M",
    "CadModel",
    "CadParts",
    "CleanReport",
    "Symmetry",
    "check_unit",
    "clean_mesh",
    "clean_model",
    "detect_unit",
    "edge_topology",
    "load_cad",
    "load_sdf_model",
    "max_pairwise_distance",
    "models_info_entry",
    "parse_pose",
    "read_cad_parts",
    "rpy_to_matrix",
    "write_model_ply_mm",
    "write_models_info",
]

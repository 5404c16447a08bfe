"""STEP / IGES files written with OpenCASCADE (``cadquery-ocp``, a dev dependency): named solids in an assembly,
in a chosen length unit, and triangle meshes turned into faceted solids (to export the subsea CAD to STEP)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

OCP_UNITS = {"mm": "MM", "m": "M", "in": "INCH", "cm": "CM"}
"""cadalign unit code -> OpenCASCADE's ``write.step.unit`` / ``write.iges.unit`` value."""


def box(size_m: tuple[float, float, float], at_m: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> object:
    """A box solid, metres (converted to the writer's unit on export)."""
    from OCP.BRepPrimAPI import BRepPrimAPI_MakeBox
    from OCP.gp import gp_Pnt

    return BRepPrimAPI_MakeBox(gp_Pnt(*(1000 * a for a in at_m)), *(1000 * s for s in size_m)).Shape()


def cylinder(radius_m: float, height_m: float, at_m: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> object:
    """A cylinder solid along +z from ``at_m``, metres."""
    from OCP.BRepPrimAPI import BRepPrimAPI_MakeCylinder
    from OCP.gp import gp_Ax2, gp_Dir, gp_Pnt

    return BRepPrimAPI_MakeCylinder(gp_Ax2(gp_Pnt(*(1000 * a for a in at_m)), gp_Dir(0, 0, 1)), 1000 * radius_m,
                                    1000 * height_m).Shape()


def mesh_solid(vertices_m: np.ndarray, faces: np.ndarray) -> object:
    """A faceted surface model (one planar face per triangle, in a compound; not sewn into a solid, which takes
    ~20 s for the panel's 5k triangles and changes nothing that is read back) of an (V, 3) / (F, 3) mesh, m."""
    from OCP.BRep import BRep_Builder
    from OCP.BRepBuilderAPI import BRepBuilderAPI_MakeFace, BRepBuilderAPI_MakePolygon
    from OCP.gp import gp_Pnt
    from OCP.TopoDS import TopoDS_Compound

    builder, compound = BRep_Builder(), TopoDS_Compound()
    builder.MakeCompound(compound)
    v = 1000.0 * np.asarray(vertices_m, float)
    for tri in np.asarray(faces):
        a, b, c = (gp_Pnt(*map(float, v[i])) for i in tri)
        poly = BRepBuilderAPI_MakePolygon(a, b, c, True)
        if not poly.IsDone():  # a degenerate triangle
            continue
        face = BRepBuilderAPI_MakeFace(poly.Wire(), True)
        if face.IsDone():
            builder.Add(compound, face.Face())
    return compound


def write_step(path: Path, parts: dict[str, object], unit: str = "mm", *, iges: bool = False) -> Path:
    """A STEP (or IGES) assembly at ``path`` with one named part per entry of ``parts`` (name -> shape in mm,
    OpenCASCADE's internal unit), written in ``unit``."""
    from OCP.IFSelect import IFSelect_RetDone
    from OCP.Interface import Interface_Static
    from OCP.STEPCAFControl import STEPCAFControl_Writer
    from OCP.STEPControl import STEPControl_AsIs
    from OCP.TCollection import TCollection_ExtendedString
    from OCP.TDataStd import TDataStd_Name
    from OCP.TDocStd import TDocStd_Document
    from OCP.XCAFDoc import XCAFDoc_DocumentTool

    doc = TDocStd_Document(TCollection_ExtendedString("XmlOcaf"))
    tool = XCAFDoc_DocumentTool.ShapeTool_s(doc.Main())
    assembly = tool.NewShape()
    TDataStd_Name.Set_s(assembly, TCollection_ExtendedString("assembly"))
    from OCP.TopLoc import TopLoc_Location

    for name, shape in parts.items():
        label = tool.AddShape(shape, False)
        TDataStd_Name.Set_s(label, TCollection_ExtendedString(name))
        comp = tool.AddComponent(assembly, label, TopLoc_Location())
        TDataStd_Name.Set_s(comp, TCollection_ExtendedString(name))
    tool.UpdateAssemblies()
    path = Path(path)
    if iges:
        from OCP.IGESCAFControl import IGESCAFControl_Writer

        Interface_Static.SetCVal_s("write.iges.unit", OCP_UNITS[unit])
        writer = IGESCAFControl_Writer()
        assert writer.Transfer(doc)
        assert writer.Write(str(path))
        return path
    Interface_Static.SetCVal_s("write.step.unit", OCP_UNITS[unit])
    writer = STEPCAFControl_Writer()
    writer.SetNameMode(True)
    assert writer.Transfer(doc, STEPControl_AsIs)
    assert writer.Write(str(path)) == IFSelect_RetDone
    return path

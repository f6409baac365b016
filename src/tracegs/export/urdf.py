"""``tracegs export --urdf DIR``: a run's rig (``rig.py``) as a URDF (``DIR/<name>.urdf``) with one
OBJ mesh per body (``DIR/meshes/``), in the scene's world frame at the handover.

The still Gaussians are the link ``world``; each body a link whose frame sits at its joint's pivot (a
free or fixed body's: its centre), turned as the world; its joint from its parent's link: ``continuous``
(a hinge), ``prismatic`` (a rail), ``planar`` (a part on no joint: it slides in the plane across its
spin axis and turns about it), ``floating`` (a free body) or ``fixed``. URDF has joint damping and dry
friction; the other terms of the identified models (stiffness, constant forces, gravity's per-body
share, floors, the state at the handover) have no URDF element: the MJCF has them, and the report
names them.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

from .hull import Hull, axis_inertia
from .rig import Rig

JOINTS = {
    "hinge": "continuous",
    "slide": "prismatic",
    "planar": "planar",
    "free": "floating",
    "fixed": "fixed",
}
RAIL_LIMIT = 1e3
"""A rail's travel either way (URDF's prismatic joints need one): unlimited in practice."""


def _vec(x) -> str:
    return " ".join(f"{float(v):.9g}" for v in np.ravel(x))


def _origin(body) -> np.ndarray:
    return np.asarray(body.pivot, float) if body.joint != "slide" else np.zeros(3)


def write_urdf(rig: Rig, hulls: list[Hull | None], folder: Path, name: str = "tracegs") -> tuple[Path, dict]:
    """Write ``folder/<name>.urdf`` and its meshes; returns the file and the report (per body: the URDF
    joint, and the terms of its model that URDF cannot hold)."""
    import trimesh

    folder = Path(folder)
    (folder / "meshes").mkdir(parents=True, exist_ok=True)
    robot = ET.Element("robot", name=name)
    ET.SubElement(robot, "link", name="world")
    report = []
    for body, hull in zip(rig.bodies, hulls, strict=True):
        origin = _origin(body)
        link = ET.SubElement(robot, "link", name=body.name)
        if hull is not None:
            inertial = ET.SubElement(link, "inertial")
            ET.SubElement(inertial, "origin", xyz=_vec(hull.centre - origin), rpy="0 0 0")
            ET.SubElement(inertial, "mass", value=f"{hull.mass:.9g}")
            i = hull.inertia
            ET.SubElement(
                inertial, "inertia", ixx=f"{i[0, 0]:.9g}", ixy=f"{i[0, 1]:.9g}", ixz=f"{i[0, 2]:.9g}",
                iyy=f"{i[1, 1]:.9g}", iyz=f"{i[1, 2]:.9g}", izz=f"{i[2, 2]:.9g}",
            )  # fmt: skip
            mesh = folder / "meshes" / f"{body.name}.obj"
            trimesh.Trimesh(hull.vertices - origin, hull.faces, process=False).export(mesh)
            for kind in ("visual", "collision"):
                element = ET.SubElement(link, kind)
                ET.SubElement(element, "origin", xyz="0 0 0", rpy="0 0 0")
                geometry = ET.SubElement(element, "geometry")
                ET.SubElement(geometry, "mesh", filename=f"meshes/{body.name}.obj")
        parent = "world" if body.parent is None else rig.bodies[body.parent].name
        parent_origin = np.zeros(3) if body.parent is None else _origin(rig.bodies[body.parent])
        joint = ET.SubElement(robot, "joint", name=body.name, type=JOINTS[body.joint])
        ET.SubElement(joint, "parent", link=parent)
        ET.SubElement(joint, "child", link=body.name)
        ET.SubElement(joint, "origin", xyz=_vec(origin - parent_origin), rpy="0 0 0")
        entry = {"body": body.name, "joint": JOINTS[body.joint], "parent": parent, "not_in_urdf": []}
        if body.joint in ("hinge", "slide", "planar"):
            ET.SubElement(joint, "axis", xyz=_vec(body.axis / np.linalg.norm(body.axis)))
        if body.joint == "slide":
            ET.SubElement(
                joint, "limit", lower=f"{-RAIL_LIMIT:g}", upper=f"{RAIL_LIMIT:g}", effort="0", velocity="0"
            )
        if body.joint in ("hinge", "slide") and body.model is not None and hull is not None:
            axis = body.axis / np.linalg.norm(body.axis)
            inertia = hull.mass if body.joint == "slide" else axis_inertia(hull, axis, body.pivot)
            c = body.coordinate
            coefs = {
                t: float(v) for t, v in zip(body.model.terms, body.model.coefficients[c], strict=True) if v
            }
            dynamics = {}
            for kind, attr in (("v", "damping"), ("sign", "friction")):
                value = -inertia * coefs.pop((kind, c), 0.0)
                if value > 0:
                    dynamics[attr] = f"{value:.9g}"
            if dynamics:
                ET.SubElement(joint, "dynamics", **dynamics)
            entry["not_in_urdf"] = [f"{kind} term of q{i}" for kind, i in coefs]
        report.append(entry)
    ET.indent(robot)
    path = folder / f"{name}.urdf"
    path.write_text('<?xml version="1.0"?>\n' + ET.tostring(robot, encoding="unicode") + "\n")
    return path, {"file": str(path), "bodies": report}

"""``tracegs export --mjcf FILE``: a run's rig (``rig.py``) as a MuJoCo model (MJCF), one file.

Every body's frame is the world frame at the handover (a free body's: at its pivot), so each joint's
axis and pivot are the rig's as they are, and the keyframe ``handover`` (at the handover time) is the
rig's state there: zero coordinates and the joints' velocities. Time is the dataset's (the clip spans
1), lengths are the scene's. Each identified model becomes MuJoCo terms, scaled by the body's inertia
about its joint (or its mass on a rail):

* ``q`` of its own coordinate: the joint's ``stiffness``, and with the constant its ``springref``;
* ``q'``: ``damping``; ``sign q'``: ``frictionloss`` (dry friction);
* a constant alone: an actuator whose affine bias is that constant force;
* ``sin q`` and ``cos q`` (a pendulum): gravity, the body's centre of mass placed where the identified
  swing puts it (its distance from the axis and its rest direction); the model's gravity is a free
  body's or a thrown part's acceleration where one falls, else the first pendulum's with its hull's
  centre of mass;
* a contact on a joint's coordinate: the joint's range, with a restitution; a thrown part's floor: a
  plane, its contact's damping set so that a bounce keeps the restitution (``contact_solref``);
* a free body's acceleration: gravity, the part of it along gravity (``gravcomp`` scales gravity per
  body; a body whose model has no gravity is compensated whole).

What has no term (drag ``q'|q'|``, the coupling between two coordinates, an acceleration across
gravity) is left out and named in the report. Parts collide with the floor only, and only those wholly
above it at the handover: their hulls overlap where they touch at joints, and a part the floor's plane
cuts through stands on it.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import xml.etree.ElementTree as ET

import numpy as np

from .hull import Hull, axis_inertia, convex_hull
from .palette import colours
from .rig import DENSITY, Body, Rig

CONTACT_TIME = 0.004
"""Duration of a bounce on the floor, in the dataset's time (the clip spans 1; a frame ~0.017)."""
FRICTION_TIME = 1e-3
"""Time constant of dry friction's constraint (MuJoCo's default, 0.02, is a frame of the clip)."""
TIMESTEP = 2e-4
"""The simulation's step, a twentieth of a contact."""


def _vec(x) -> str:
    return " ".join(f"{float(v):.9g}" for v in np.ravel(x))


def _rebound(stiffness: float, damping: float) -> float:
    """The fraction of its speed a ball keeps off a plane whose contact is MuJoCo's direct ``solref``
    ``-stiffness -damping`` (per unit mass), simulated."""
    import mujoco

    xml = f"""<mujoco><option timestep="{TIMESTEP}" gravity="0 0 0" integrator="RK4"/><worldbody>
    <geom type="plane" size="0 0 1" condim="1" solref="{-stiffness} {-damping}"/>
    <body pos="0 0 0.1"><freejoint/><geom type="sphere" size="0.05"/></body></worldbody></mujoco>"""
    model = mujoco.MjModel.from_xml_string(xml)
    data = mujoco.MjData(model)
    data.qvel[2] = -1.0
    while data.time < 0.1 + 20 * CONTACT_TIME:
        mujoco.mj_step(model, data)
    return float(data.qvel[2])


@functools.lru_cache(maxsize=64)
def contact_solref(restitution: float) -> tuple[float, float]:
    """``(stiffness, damping)`` of MuJoCo's direct ``solref`` for a contact lasting about
    ``CONTACT_TIME`` that returns the fraction ``restitution`` of the speed it hits with. MuJoCo has no
    restitution: its soft contact is a spring-damper whose rebound differs from the damped oscillator's
    ``e = exp(-pi zeta / sqrt(1 - zeta^2))``, so the damping is found by bisection on a simulated
    bounce (each ~1 ms)."""
    e = min(max(float(restitution), 0.0), 1.0)
    stiffness = (math.pi / CONTACT_TIME) ** 2
    low, high = 0.0, 4 * math.sqrt(stiffness)  # the rebound falls as the damping grows
    for _ in range(30):
        mid = 0.5 * (low + high)
        low, high = (mid, high) if _rebound(stiffness, mid) > e else (low, mid)
    return stiffness, 0.5 * (low + high)


def _solref(restitution: float) -> str:
    stiffness, damping = contact_solref(round(float(restitution), 4))
    return _vec([-stiffness, -damping])


def scene_gravity(rig: Rig, hulls: list[Hull | None]) -> tuple[np.ndarray, str]:
    """The model's gravity [3] and where it comes from (module docstring)."""
    falling = [
        b.acceleration for b in rig.bodies if b.acceleration is not None and b.source != "learned physics"
    ]
    falling = [a for a in falling if np.linalg.norm(a) > 0]
    if falling:
        return falling[0], "the acceleration of a free or thrown part"
    down = -rig.up / np.linalg.norm(rig.up)
    for body, hull in zip(rig.bodies, hulls, strict=True):
        swing = _swing(body)
        if swing is None or hull is None:
            continue
        axis = body.axis / np.linalg.norm(body.axis)
        r = hull.centre - body.pivot
        r_perp = np.linalg.norm(r - (r @ axis) * axis)
        across = np.linalg.norm(down - (down @ axis) * axis)
        if r_perp > 0 and across > 0.1:
            g = swing[0] * axis_inertia(hull, axis, body.pivot) / (hull.mass * r_perp * across)
            return down * g, "the swing of the first pendulum, with its hull's centre of mass"
    return np.zeros(3), "no part falls or swings: none"


def _swing(body: Body) -> tuple[float, float] | None:
    """``(A, phi)`` of a hinge model's ``a sin q + b cos q`` of its own coordinate, in the joint's
    coordinate from the handover ``s = q - q_end``: ``A sin(s + phi)``; None without those terms."""
    if body.joint != "hinge" or body.model is None:
        return None
    a = b = 0.0
    c = body.coordinate
    for (kind, i), coef in zip(body.model.terms, body.model.coefficients[c], strict=True):
        if i == c and kind == "sin":
            a += coef
        elif i == c and kind == "cos":
            b += coef
    if a == 0 and b == 0:
        return None
    q_end = float(body.model.q_end[c])
    return math.hypot(a, b), math.atan2(b, a) + q_end


def _pendulum_centre(body: Body, hull: Hull, gravity: np.ndarray) -> np.ndarray | None:
    """Where the centre of mass of ``body`` (a hinge with a swing) puts the swing ``A sin(s + phi)``
    under ``gravity``: at distance ``r`` from the axis, ``m |g_perp| r / I(r) = A``, and at rest where
    the swing is; None where gravity lies along the axis or no ``r`` does it."""
    amplitude, phi = _swing(body)
    axis = body.axis / np.linalg.norm(body.axis)
    g_perp = gravity - (gravity @ axis) * axis
    g = float(np.linalg.norm(g_perp))
    if g < 1e-12:
        return None
    i_c = float(axis @ hull.inertia @ axis)
    m = hull.mass
    disc = (m * g) ** 2 - 4 * amplitude**2 * m * i_c
    if disc < 0:
        return None
    r = (m * g - math.sqrt(disc)) / (2 * amplitude * m)
    down = g_perp / g
    # at rest (s* = pi - phi, where A sin(s + phi) falls through 0) it hangs along ``down``: at the
    # handover it points along ``down`` turned back by s*
    cos, sin = math.cos(phi - math.pi), math.sin(phi - math.pi)
    direction = down * cos + np.cross(axis, down) * sin + axis * (axis @ down) * (1 - cos)
    along = (hull.centre - body.pivot) @ axis
    return body.pivot + along * axis + r * direction


def _inertial(parent: ET.Element, hull: Hull | None, centre: np.ndarray | None, frame: np.ndarray) -> None:
    if hull is None:  # a frame that only carries (a turntable whose own Gaussians keep the learned physics)
        ET.SubElement(parent, "inertial", pos="0 0 0", mass="1e-6", diaginertia="1e-9 1e-9 1e-9")
        return
    c = (hull.centre if centre is None else centre) - frame
    i = hull.inertia
    full = [i[0, 0], i[1, 1], i[2, 2], i[0, 1], i[0, 2], i[1, 2]]
    ET.SubElement(parent, "inertial", pos=_vec(c), mass=f"{hull.mass:.9g}", fullinertia=_vec(full))


def _frame(body: Body) -> np.ndarray:
    """Where a body's frame is in the world at the handover (turned as the world): a free body's at its
    pivot, every other one's at the origin."""
    return body.pivot if body.joint == "free" else np.zeros(3)


class _Writer:
    def __init__(self, rig: Rig, hulls: list[Hull | None]):
        self.rig, self.hulls = rig, hulls
        self.gravity, self.gravity_source = scene_gravity(rig, hulls)
        self.root = ET.Element("mujoco", model="tracegs")
        ET.SubElement(self.root, "compiler", angle="radian", autolimits="true")
        ET.SubElement(
            self.root, "option", timestep=f"{TIMESTEP:g}", gravity=_vec(self.gravity), integrator="RK4"
        )
        self.asset = ET.SubElement(self.root, "asset")
        self.world = ET.SubElement(self.root, "worldbody")
        self.actuators: list[ET.Element] = []
        self.qpos: list[float] = []
        self.qvel: list[float] = []
        self.report: list[dict] = []
        self.plane: tuple[np.ndarray, float] | None = None

    def terms(self, body: Body, inertia: float, joint: ET.Element, name: str) -> list[str]:
        """Set ``joint``'s terms from the model of ``body`` (module docstring); what is left out."""
        model, c, left = body.model, body.coordinate, []
        if model is None:
            return left
        coefs = {
            (kind, i): float(v) for (kind, i), v in zip(model.terms, model.coefficients[c], strict=True) if v
        }
        c_q, constant = coefs.pop(("q", c), 0.0), coefs.pop(("1", -1), 0.0)
        q_end = float(model.q_end[c])
        if c_q:  # -k (s - ref) = I (c1 + c_q q), q = s + q_end
            joint.set("stiffness", f"{-inertia * c_q:.9g}")
            joint.set("springref", f"{-(constant + c_q * q_end) / c_q:.9g}")
            if c_q > 0:
                left.append(f"q{c}'s stiffness is negative (it pushes away from rest)")
        elif constant:
            self.actuators.append(
                ET.Element("general", name=f"{name}_force", joint=name, gainprm="0", biastype="affine",
                           biasprm=_vec([inertia * constant, 0, 0]))
            )  # fmt: skip
        for kind, attr in (("v", "damping"), ("sign", "frictionloss")):
            value = -inertia * coefs.pop((kind, c), 0.0)
            if value > 0:
                joint.set(attr, f"{value:.9g}")
                if attr == "frictionloss":  # stiff: MuJoCo's default time constant is 1.2 frames here
                    joint.set("solreffriction", _vec([FRICTION_TIME, 1]))
            elif value < 0:
                left.append(f"{kind} term of q{c} with the wrong sign for {attr}")
        coefs.pop(("sin", c), None), coefs.pop(("cos", c), None)
        left += [f"{kind} term of q{i}" for (kind, i) in coefs]
        for contact in model.contacts:
            if contact.coordinate == c:
                bound = contact.position - float(model.q_end[c])
                joint.set("range", _vec([-1e9, bound] if contact.direction > 0 else [bound, 1e9]))
                joint.set("solreflimit", _solref(contact.restitution))
        return left

    def subtree(self, k: int) -> list[int]:
        """Body ``k`` and every body it carries."""
        out = [k]
        for j, body in enumerate(self.rig.bodies):
            if body.parent == k:
                out += self.subtree(j)
        return out

    def carried_inertia(self, k: int, axis: np.ndarray | None, centres: dict) -> float:
        """The mass (``axis`` None) or the moment of inertia about body ``k``'s joint axis of the bodies it
        moves (itself and those it carries, as they are at the handover)."""
        total = 0.0
        for j in self.subtree(k):
            hull = self.hulls[j]
            if hull is not None:
                pivot = self.rig.bodies[k].pivot
                total += hull.mass if axis is None else axis_inertia(hull, axis, pivot, centres.get(j))
        return max(total, 1e-9)

    def body(self, parent: ET.Element, k: int, centres: dict) -> None:
        body, hull = self.rig.bodies[k], self.hulls[k]
        frame = _frame(body)
        carrier = np.zeros(3) if body.parent is None else _frame(self.rig.bodies[body.parent])
        element = ET.SubElement(parent, "body", name=body.name, pos=_vec(frame - carrier))
        _inertial(element, hull, centres.get(k), frame)
        entry = {"body": body.name, "joint": body.joint, "source": body.source, "why": body.why}
        entry["left_out"] = list(body.left_out)
        entry["parent"] = None if body.parent is None else self.rig.bodies[body.parent].name
        gravity = float(np.linalg.norm(self.gravity))
        compensated = 1.0
        if body.joint in ("hinge", "slide"):
            axis = body.axis / np.linalg.norm(body.axis)
            joint = ET.SubElement(
                element, "joint", name=body.name, type=body.joint, pos=_vec(body.pivot), axis=_vec(axis)
            )
            inertia = self.carried_inertia(k, axis if body.joint == "hinge" else None, centres)
            entry["left_out"] += self.terms(body, inertia, joint, body.name)
            if _swing(body) is not None:
                if k in centres:
                    compensated = 0.0
                else:
                    entry["left_out"].append("the swing (sin q, cos q): gravity cannot turn this hinge")
            entry.update(axis=axis.tolist(), pivot=body.pivot.tolist(), inertia=inertia)
            self.qpos.append(0.0)
            self.qvel.append(float(body.velocity[0]))
        elif body.joint == "planar":
            mass = self.carried_inertia(k, None, centres)
            for i, direction in enumerate(body.basis):
                name = f"{body.name}_{i}"
                joint = ET.SubElement(
                    element, "joint", name=name, type="slide", pos=_vec(body.pivot), axis=_vec(direction)
                )
                moved = dataclasses.replace(body, coordinate=i, joint="slide")
                entry["left_out"] += self.terms(moved, mass, joint, name)
                self.qpos.append(0.0)
                self.qvel.append(float(body.velocity[i]))
            ET.SubElement(
                element,
                "joint",
                name=f"{body.name}_spin",
                type="hinge",
                pos=_vec(body.pivot),
                axis=_vec(body.axis),
            )
            self.qpos.append(0.0)
            self.qvel.append(float(body.velocity[-1]))
            entry.update(basis=body.basis.tolist(), axis=body.axis.tolist(), pivot=body.pivot.tolist())
        elif body.joint == "free":
            ET.SubElement(element, "freejoint", name=body.name)
            self.qpos += [*body.pivot, 1.0, 0.0, 0.0, 0.0]
            self.qvel += [float(v) for v in body.velocity]
            a = np.zeros(3) if body.acceleration is None else body.acceleration
            if gravity > 0:
                along = float(a @ self.gravity) / gravity
                compensated = 1.0 - along / gravity
                across = a - along * self.gravity / gravity
                if np.linalg.norm(across) > 1e-3 * max(np.linalg.norm(a), 1e-12):
                    entry["left_out"].append(
                        f"an acceleration of {np.linalg.norm(across):.3g} across gravity"
                    )
            elif np.linalg.norm(a) > 0:
                entry["left_out"].append("its acceleration (the model has no gravity)")
            entry.update(pivot=body.pivot.tolist())
        if compensated != 0.0:
            element.set("gravcomp", f"{compensated:.9g}")
        if hull is not None:
            ET.SubElement(
                self.asset, "mesh", name=body.name, vertex=_vec(hull.vertices - frame), face=_vec(hull.faces)
            )
            above = self.plane is not None and bool(
                (hull.vertices @ self.plane[0] >= self.plane[1] - 1e-6 * np.ptp(hull.vertices)).all()
            )
            collides = {"contype": "2", "conaffinity": "1"}
            bits = collides if above and body.floor is None else {"contype": "0", "conaffinity": "0"}
            rgba = _vec([*colours(len(self.rig.bodies) + 1, True)[k + 1], 1.0])  # tracegs segment's palette
            ET.SubElement(element, "geom", type="mesh", mesh=body.name, density="0", rgba=rgba, **bits)
            if body.floor is not None:  # it hits its floor as a ball (``rig.Body.floor``), not shown
                radius = f"{body.floor['radius']:.9g}"
                ET.SubElement(
                    element, "geom", type="sphere", size=radius, density="0", rgba="0 0 0 0", **collides
                )
            entry.update(
                mass=hull.mass, centre_of_mass=(hull.centre if k not in centres else centres[k]).tolist()
            )
        self.report.append(entry)
        for j, child in enumerate(self.rig.bodies):
            if child.parent == k:
                self.body(element, j, centres)

    def floor(self) -> None:
        """The first thrown part's floor, a plane that the bodies wholly above it at the handover hit."""
        floor = next((b.floor for b in self.rig.bodies if b.floor is not None), None)
        if floor is None:
            return
        normal = np.asarray(floor["normal"], float) / np.linalg.norm(floor["normal"])
        self.plane = (normal, float(floor["offset"]))
        ET.SubElement(
            self.world, "geom", name="floor", type="plane", size="0 0 1", pos=_vec(normal * floor["offset"]),
            zaxis=_vec(normal), condim="1", priority="1", contype="1", conaffinity="2",
            solref=_solref(floor["restitution"]),
        )  # fmt: skip

    def write(self) -> tuple[str, dict]:
        centres = {}
        for k, (body, hull) in enumerate(zip(self.rig.bodies, self.hulls, strict=True)):
            if _swing(body) is not None and hull is not None:
                centre = _pendulum_centre(body, hull, self.gravity)
                if centre is not None:
                    centres[k] = centre
            elif body.joint in ("planar", "free") and hull is not None:  # its model's centre
                centres[k] = body.pivot
        self.floor()
        for k, body in enumerate(self.rig.bodies):
            if body.parent is None:
                self.body(self.world, k, centres)
        if self.actuators:
            actuator = ET.SubElement(self.root, "actuator")
            actuator.extend(self.actuators)
        keyframe = ET.SubElement(self.root, "keyframe")
        key = ET.SubElement(keyframe, "key", name="handover", time=f"{self.rig.t0:.9g}")
        if self.qpos:
            key.set("qpos", _vec(self.qpos))
            key.set("qvel", _vec(self.qvel))
        ET.indent(self.root)
        report = {
            "gravity": self.gravity.tolist(),
            "gravity_from": self.gravity_source,
            "density": DENSITY,
            "handover": self.rig.t0,
            "time": "the dataset's (the clip spans 1)",
            "bodies": self.report,
        }
        return ET.tostring(self.root, encoding="unicode"), report


def rig_hulls(rig: Rig) -> list[Hull | None]:
    """Each body's hull at ``DENSITY`` (None: a body with fewer than 4 Gaussians, a frame only)."""
    return [convex_hull(body.points, DENSITY) for body in rig.bodies]


def mjcf_text(rig: Rig, hulls: list[Hull | None] | None = None) -> tuple[str, dict]:
    """The MJCF of ``rig`` and its report (module docstring)."""
    return _Writer(rig, rig_hulls(rig) if hulls is None else hulls).write()

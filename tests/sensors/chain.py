"""A test serial machine (a column turning about z, a telescopic stage, an arm on a horizontal axis) and an
independent forward kinematics for it: 4x4 products written from the joint definitions with scipy's rotations,
not bayescal's chain code."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

# (type, origin mm, rpy rad, axis); the truth geometry is the nominal one plus errors written into the file
JOINTS = (
    ("revolute", [0.0, 0.0, 200.0], [0.0, 0.0, 0.0], [0.0, 0.0, 1.0]),
    ("prismatic", [0.0, 0.0, 300.0], [0.0, 0.0, 0.0], [0.0, 0.0, 1.0]),
    ("revolute", [100.0, 0.0, 50.0], [0.3, 0.0, 0.0], [0.0, 1.0, 0.0]),
)
TOOL = [300.0, 0.0, 0.0]
LIMITS = [[-3.0, 3.0], [0.0, 500.0], [-1.0, 1.0]]


def machine_text(joints=JOINTS, sigma_tilt=2.0e-5, extra="", tool=TOOL, sigma_position=0.005) -> str:
    """The machine file of ``joints`` (a list like :data:`JOINTS`)."""
    out = ['kind = "serial"', 'name = "sensor test column"', ""]
    for t, o, r, a in joints:
        out += ["[[joint]]", f'type = "{t}"', f"origin = {list(map(float, o))}", f"rpy = {list(map(float, r))}",
                f"axis = {list(map(float, a))}", ""]
    out += ["[tool]", f"point = {list(map(float, tool))}", "", "[measurement]", f"sigma_position = {sigma_position}", "sigma_angle = 5.0e-5",
            f"sigma_tilt = {sigma_tilt}", extra, "", "[workspace]", f"q_limits = {LIMITS}", ""]
    return "\n".join(out)


def transforms(joints, q: np.ndarray, tool=TOOL) -> tuple[list[np.ndarray], np.ndarray]:
    """Per pose, the 4x4 frame after every joint (base frame) and the tool point: an independent product."""
    q = np.atleast_2d(q)
    frames, points = [], []
    for qi in q:
        T = np.eye(4)
        after = []
        for (t, o, r, a), x in zip(joints, qi):
            F = np.eye(4)
            F[:3, 3] = o
            F[:3, :3] = Rotation.from_euler("xyz", r).as_matrix()  # extrinsic x, y, z: Rz(y) Ry(p) Rx(r)
            M = np.eye(4)
            a = np.asarray(a, float) / np.linalg.norm(a)
            if t == "revolute":
                M[:3, :3] = Rotation.from_rotvec(a * x).as_matrix()
            else:
                M[:3, 3] = a * x
            T = T @ F @ M
            after.append(T.copy())
        frames.append(after)
        points.append((T @ np.r_[tool, 1.0])[:3])
    return frames, np.array(points)


def poses(n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    lim = np.array(LIMITS)
    return lim[:, 0] + (lim[:, 1] - lim[:, 0]) * rng.uniform(size=(n, 3))

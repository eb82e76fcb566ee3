"""Our own objects: cups (a ring of box walls on a disc) and the three-drawer cabinet.

The cabinet MJCF is generated here, written once next to the package
(``sim/assets/cabinet.xml`` is the committed copy), and loaded as a robosuite
``MujocoXMLObject`` without a free joint, so it is fixed to the table.
"""

from __future__ import annotations

import os
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

ASSETS = Path(__file__).parent / "assets"


@dataclass(frozen=True)
class CupGeometry:
    inner_radius: float
    outer_radius: float
    height: float
    bottom: float = 0.006  # floor thickness
    walls: int = 16

    @property
    def half_height(self) -> float:
        return self.height / 2


def make_cup(name: str, geometry: CupGeometry, rgba: tuple[float, ...], density: float):
    """A cup as a robosuite CompositeObject; its frame is at the cup's centre."""
    from robosuite.models.objects import CompositeObject

    g = geometry
    n = g.walls
    wall_half_thick = (g.outer_radius - g.inner_radius) / 2
    mid_r = (g.outer_radius + g.inner_radius) / 2
    wall_half_width = g.outer_radius * np.tan(np.pi / n) + 0.001
    types, sizes, locs, quats, names = [], [], [], [], []
    for i in range(n):
        a = 2 * np.pi * i / n
        types.append("box")
        sizes.append((wall_half_thick, wall_half_width, g.half_height))
        locs.append((mid_r * np.cos(a), mid_r * np.sin(a), 0.0))
        quats.append((np.cos(a / 2), 0.0, 0.0, np.sin(a / 2)))
        names.append(f"wall{i}")
    types.append("cylinder")
    sizes.append((g.outer_radius, g.bottom / 2))
    locs.append((0.0, 0.0, -g.half_height + g.bottom / 2))
    quats.append((1.0, 0.0, 0.0, 0.0))
    names.append("bottom")
    k = len(types)
    return CompositeObject(
        name=name,
        total_size=(g.outer_radius, g.outer_radius, g.half_height),
        geom_types=types,
        geom_sizes=sizes,
        geom_locations=locs,
        geom_quats=quats,
        geom_names=names,
        geom_rgbas=[rgba] * k,
        geom_frictions=[(1.0, 0.005, 0.0001)] * k,
        geom_condims=[4] * k,
        density=density,
        locations_relative_to_center=True,
        obj_types="all",
    )


# -- cabinet -----------------------------------------------------------------


@dataclass(frozen=True)
class CabinetGeometry:
    """Three drawers side by side (y), fronts facing the robot (-x)."""

    drawer_width: float = 0.10  # along y
    drawer_depth: float = 0.16  # along x
    drawer_height: float = 0.07  # along z
    wall: float = 0.01
    gap: float = 0.002
    travel: float = 0.20  # slide range
    handle_length: float = 0.045  # along x, out of the drawer front
    handle_half_width: float = 0.009  # along y, what the fingers close on
    handle_half_height: float = 0.012
    handle_drop: float = 0.022  # handle centre below the drawer top
    drawers: int = 3

    @property
    def pitch(self) -> float:
        return self.drawer_width + 2 * self.gap + self.wall

    def drawer_y(self, i: int) -> float:
        """Drawer i's centre along y in the cabinet frame; 0 is the robot's right (-y)."""
        return (i - (self.drawers - 1) / 2) * self.pitch

    @property
    def body_height(self) -> float:
        return self.drawer_height + 2 * self.gap + 2 * self.wall

    def handle_offset(self) -> np.ndarray:
        """Handle centre relative to the drawer body frame."""
        return np.array(
            [
                -self.drawer_depth / 2 - self.handle_length / 2,
                0.0,
                self.drawer_height / 2 - self.handle_drop,
            ]
        )


DRAWER_COLORS = ("0.75 0.3 0.25 1", "0.3 0.6 0.3 1", "0.25 0.4 0.75 1")


def _box(name: str, pos, size, attrs: str) -> str:
    p = " ".join(f"{v:.5f}" for v in pos)
    s = " ".join(f"{v:.5f}" for v in size)
    return f'        <geom group="0" name="{name}" type="box" pos="{p}" size="{s}" {attrs}/>'


def cabinet_xml(geom: CabinetGeometry = CabinetGeometry()) -> str:
    """MJCF for the cabinet; its frame is at the centre of its floor panel's top."""
    g = geom
    inner_w = g.drawers * g.pitch - g.wall
    half_w = inner_w / 2 + g.wall
    depth = g.drawer_depth + 2 * g.gap
    hz = g.body_height / 2
    wood = 'rgba="0.55 0.42 0.3 1" friction="1 0.005 0.0001" solref="0.02 1" density="500"'
    lines = [
        '<mujoco model="cabinet">',
        "  <worldbody>",
        "    <body>",
        '      <body name="object">',
        # floor, roof, back, sides
        _box("floor", (0, 0, -g.wall / 2), (depth / 2 + g.wall, half_w, g.wall / 2), wood),
        _box("roof", (0, 0, 2 * hz - g.wall * 1.5), (depth / 2 + g.wall, half_w, g.wall / 2), wood),
        _box("back", (depth / 2 + g.wall / 2, 0, hz - g.wall), (g.wall / 2, half_w, hz), wood),
    ]
    for k, y in enumerate(
        [-(inner_w / 2 + g.wall / 2)]
        + [g.drawer_y(i) + g.pitch / 2 for i in range(g.drawers - 1)]
        + [inner_w / 2 + g.wall / 2]
    ):
        lines.append(_box(f"side{k}", (0, y, hz - g.wall), (depth / 2, g.wall / 2, hz - g.wall), wood))
    h = g.handle_offset()
    for i in range(g.drawers):
        y = g.drawer_y(i)
        z = g.gap + g.drawer_height / 2
        color = DRAWER_COLORS[i % len(DRAWER_COLORS)]
        lines += [
            f'        <body name="drawer{i}" pos="0 {y:.5f} {z:.5f}">',
            f'          <joint name="slide{i}" type="slide" axis="-1 0 0" range="0 {g.travel}" '
            f'limited="true" damping="8" frictionloss="0.5" armature="0.01"/>',
            f'          <geom group="0" name="box{i}" type="box" size="{g.drawer_depth / 2} {g.drawer_width / 2} '
            f'{g.drawer_height / 2}" rgba="{color}" density="300" friction="1 0.005 0.0001"/>',
            f'          <geom group="0" name="handle{i}" type="box" pos="{h[0]:.5f} 0 {h[2]:.5f}" '
            f'size="{g.handle_length / 2} {g.handle_half_width} {g.handle_half_height}" '
            f'rgba="0.85 0.85 0.85 1" density="300" friction="1.5 0.005 0.0001" condim="4"/>',
            f'          <site name="handle_site{i}" pos="{h[0]:.5f} 0 {h[2]:.5f}" size="0.004" rgba="1 0 0 0"/>',
            "        </body>",
        ]
    lines += [
        "      </body>",
        '      <site name="bottom_site" pos="0 0 0" size="0.005" rgba="0 0 0 0"/>',
        f'      <site name="top_site" pos="0 0 {2 * hz}" size="0.005" rgba="0 0 0 0"/>',
        f'      <site name="horizontal_radius_site" pos="{depth / 2} {half_w} 0" size="0.005" rgba="0 0 0 0"/>',
        "    </body>",
        "  </worldbody>",
        "</mujoco>",
        "",
    ]
    return "\n".join(lines)


def cabinet_path(geom: CabinetGeometry = CabinetGeometry()) -> Path:
    """The committed cabinet MJCF (``hitl`` regenerates it if the generator changed).

    Falls back to a private temporary copy when the package folder is read-only.
    """
    text = cabinet_xml(geom)
    path = ASSETS / "cabinet.xml"
    if path.exists() and path.read_text() == text:
        return path
    try:
        path.write_text(text)
    except OSError:
        fd, tmp = tempfile.mkstemp(prefix="hitl-cabinet-", suffix=".xml")
        with os.fdopen(fd, "w") as f:
            f.write(text)
        path = Path(tmp)
    return path


def make_cabinet(name: str, geom: CabinetGeometry = CabinetGeometry()):
    from robosuite.models.objects import MujocoXMLObject

    return MujocoXMLObject(str(cabinet_path(geom)), name=name, joints=None, obj_type="all")

"""The robot's camera views in a browser's panel: its front and wrist cameras as ``server.cameras`` renders
them, beside the 3D view, as an operator of a real robot sees them; or why there are none."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import viser

from server.cameras import CameraView
from server.errors import ServiceError
from server.port import FleetPort
from sim.cameras import CAMERAS, DEFAULT_SIZE
from web.viser_internals import show_jpeg


class CameraFolder:
    """``show(robot_id)`` at each tick: asking for the views keeps the robot watched (rendered); the images
    are sent only when a new view came. ``set_once(handle, attr, value)`` is the panel's send-if-changed."""

    def __init__(self, gui: viser.GuiApi, fleet: FleetPort, set_once: Callable) -> None:
        self.fleet, self._set = fleet, set_once
        with gui.add_folder("Cameras"):
            self.status = gui.add_markdown("")
            blank = np.full((DEFAULT_SIZE[1], DEFAULT_SIZE[0], 3), 235, np.uint8)
            self.images = {name: gui.add_image(blank, label=name) for name in CAMERAS}
        self._shown: tuple = ()  # (robot, when rendered) of the views on screen

    def show(self, robot_id: int) -> None:
        try:
            cam = self.fleet.camera_view(robot_id)
        except ServiceError as exc:
            cam = CameraView(False, exc.message)
        images = cam.images if cam.available else None
        for handle in self.images.values():  # hidden only when there will be none: no layout jumps meanwhile
            self._set(handle, "visible", cam.available)
        if not cam.available:
            self._set(self.status, "content", f"_Camera views unavailable: {cam.reason}_")
            return
        if images is None:
            self._set(self.status, "content", "_Camera views: the renderer is starting…_")
            return
        if (robot_id, images.rendered_at) != self._shown:
            for name, handle in self.images.items():
                show_jpeg(handle, images.images[name])
            self._shown = (robot_id, images.rendered_at)
        text = f"Front and wrist cameras, {images.width}×{images.height} at {cam.hz:g} Hz · episode step {images.clock}"
        self._set(self.status, "content", text)

"""The camera renderer's process (``python -m server.camera_worker``): renders robots' camera views for
``server.cameras.CameraFeed``, which starts it, away from the fleet's process.

Its own process because OpenGL is process-wide state: a software context (OSMesa, ``MUJOCO_GL``
chosen before ``mujoco`` is imported, which only a fresh process guarantees) that fails or crashes
takes this process down, not the fleet. It keeps one ``sim.cameras.CameraRig`` per task for its life:
with PyOpenGL's OSMesa, freeing one context while another renders leaves the other drawing nothing.

Protocol on stdin / stdout: length-prefixed (4 bytes, big-endian) msgpack messages. First it writes
``{"ready": true, "gl": "<backend>"}``. Each request ``{"task", "qpos" (float64 bytes), "placed" (model
body -> position and quaternion xyzw, 7 numbers: ``sim.frame.RobotFrame.placed``), "width", "height",
"quality"}`` is answered with ``{"images": {camera: JPEG bytes}}`` or ``{"error": "..."}``.
It exits at end of input.
"""

from __future__ import annotations

import io
import os
import struct
import sys

HEADER = struct.Struct(">I")
MAX_MESSAGE = 64 * 1024 * 1024


def read_message(stream) -> bytes | None:
    """One length-prefixed message from a binary stream; None at end of input."""
    head = stream.read(HEADER.size)
    if len(head) < HEADER.size:
        return None
    (n,) = HEADER.unpack(head)
    if n > MAX_MESSAGE:
        raise ValueError(f"a message of {n} bytes is over the limit of {MAX_MESSAGE}")
    body = stream.read(n)
    if len(body) < n:
        return None
    return body


def write_message(stream, body: bytes) -> None:
    stream.write(HEADER.pack(len(body)) + body)
    stream.flush()


NICENESS = 10  # below the fleet's physics and control


def main() -> int:
    os.nice(NICENESS)
    os.environ.setdefault("MUJOCO_GL", "osmesa")  # before mujoco is imported: no display here
    import msgspec

    stdin, stdout = sys.stdin.buffer, sys.stdout.buffer
    sys.stdout = sys.stderr  # what libraries print must not corrupt the protocol
    encode, decode = msgspec.msgpack.encode, msgspec.msgpack.decode
    gl = os.environ["MUJOCO_GL"]
    try:  # an OpenGL context at all: kept for the process's life (see the module)
        import mujoco

        probe = mujoco.GLContext(8, 8)
        probe.make_current()
    except Exception as exc:  # noqa: BLE001 - whatever stops OpenGL, said in the answer
        why = f"no OpenGL context ({gl}): {type(exc).__name__}: {exc}"
        write_message(stdout, encode({"ready": False, "error": why}))
        return 1
    import numpy as np
    from PIL import Image

    from sim.cameras import CameraRig
    from sim.registry import make_task

    rigs: dict[tuple[str, int, int], CameraRig] = {}
    write_message(stdout, encode({"ready": True, "gl": gl}))
    while (body := read_message(stdin)) is not None:
        try:
            job = decode(body)
            key = (str(job["task"]), int(job["width"]), int(job["height"]))
            if key not in rigs:
                task = make_task(key[0])
                try:
                    rigs[key] = CameraRig(task.mj_model(), key[1], key[2])
                finally:
                    task.close()
            placed = {name: (np.asarray(p[:3]), np.asarray(p[3:])) for name, p in (job.get("placed") or {}).items()}
            images = rigs[key].render(np.frombuffer(job["qpos"], dtype=np.float64), placed)
            out = {}
            for name, rgb in images.items():
                buf = io.BytesIO()
                Image.fromarray(rgb).save(buf, format="JPEG", quality=int(job.get("quality", 80)))
                out[name] = buf.getvalue()
            reply = {"images": out}
        except Exception as exc:  # noqa: BLE001 - a bad request is answered, and the process goes on
            reply = {"error": f"{type(exc).__name__}: {exc}"[:500]}
        write_message(stdout, encode(reply))
    return 0


if __name__ == "__main__":
    sys.exit(main())

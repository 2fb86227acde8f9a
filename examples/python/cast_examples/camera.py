"""The demo with a real camera driver (``make demo-ros``, docs/ros.md): the table as a picture, and its readers.

- :func:`write_table_picture` draws the demo's table (``scene.make_scene``) as
  a PNG: each object its colour and shape on a white table, nearer objects
  lower in the picture. ROS 1's ``image_publisher`` driver publishes it as
  ``sensor_msgs/Image`` frames, which the ROS bridge writes into the vision WM.
- :class:`ImageSegmenter` reads each frame (an ``ros1.sensor_msgs.msg.Image``
  entry, decoded with the types ``cast ros-types`` generated), finds the
  regions of colour in the pixels and keeps one ``SceneObject`` per region up
  to date, with the features the recognisers name colours and shapes from.
- :class:`AnswerAnnouncer` turns every answered ``Question`` into a
  ``ros1.std_msgs.msg.String`` entry, which the bridge publishes on a ROS topic.

No imaging library: PNG is written with zlib, and the picture is small.
"""

from __future__ import annotations

import struct
import zlib
from pathlib import Path
from typing import Any

from castdemo.scene_pb2 import Question, SceneObject
from ros1.sensor_msgs.msg.image_pb2 import Image
from ros1.std_msgs.msg.string_pb2 import String

import cast
from cast_examples.scene import COLOURS, TrueObject, make_scene

__all__ = ["AnswerAnnouncer", "ImageSegmenter", "regions", "write_table_picture"]

WIDTH, HEIGHT = 320, 240
BACKGROUND = (0.97, 0.97, 0.95)


def _to_pixel(x: float, y: float) -> tuple[float, float]:
    """Table metres (x right, y away from the robot) to a pixel (column, row): far objects higher up."""
    return (x + 0.8) / 1.6 * WIDTH, HEIGHT - (y / 1.0) * HEIGHT


def _to_table(column: float, row: float) -> tuple[float, float]:
    return column / WIDTH * 1.6 - 0.8, (HEIGHT - row) / HEIGHT


def _inside(obj: TrueObject, column: float, row: float) -> bool:
    cx, cy = _to_pixel(obj.x, obj.y)
    r = obj.size / 1.6 * WIDTH  # the object's size (m) as a radius in pixels: a clearly visible region
    dx, dy = column - cx, row - cy
    if obj.shape == "ball":
        return dx * dx + dy * dy <= r * r
    if obj.shape == "cube":
        return abs(dx) <= r and abs(dy) <= r
    # cone: a triangle, apex up
    return -r <= dy <= r and abs(dx) <= (dy + r) / 2


def table_pixels(objects: list[TrueObject]) -> bytes:
    """The table as RGB bytes, row by row (the first object drawn last, on top)."""
    out = bytearray(bytes(round(c * 255) for c in BACKGROUND) * (WIDTH * HEIGHT))
    for obj in reversed(objects):
        cx, cy = _to_pixel(obj.x, obj.y)
        r = int(obj.size / 1.6 * WIDTH) + 2
        colour = bytes(round(c * 255) for c in COLOURS[obj.colour])
        for row in range(max(0, int(cy) - r), min(HEIGHT, int(cy) + r + 1)):
            for column in range(max(0, int(cx) - r), min(WIDTH, int(cx) + r + 1)):
                if _inside(obj, column + 0.5, row + 0.5):
                    out[(row * WIDTH + column) * 3:(row * WIDTH + column + 1) * 3] = colour
    return bytes(out)


def write_table_picture(path: Path, objects: int = 6, seed: int = 7) -> None:
    """Draw the demo's table (its first ``objects`` objects) as a PNG at ``path``."""
    rgb = table_pixels(make_scene(objects, seed))
    rows = b"".join(b"\x00" + rgb[r * WIDTH * 3:(r + 1) * WIDTH * 3] for r in range(HEIGHT))

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)

    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", WIDTH, HEIGHT, 8, 2, 0, 0, 0))
                     + chunk(b"IDAT", zlib.compress(rows)) + chunk(b"IEND", b""))


def regions(image: Image) -> list[dict[str, float]]:
    """The regions of colour in a ``bgr8`` or ``rgb8`` frame: centre (m), size (m), mean RGB, fill, corners."""
    width, height, step = image.width, image.height, image.step
    order = (2, 1, 0) if image.encoding == "bgr8" else (0, 1, 2)
    data = image.data
    labels = [-1] * (width * height)

    def rgb(i: int) -> tuple[int, int, int]:
        base = (i // width) * step + (i % width) * 3
        return data[base + order[0]], data[base + order[1]], data[base + order[2]]

    def background(c: tuple[int, int, int]) -> bool:
        return min(c) > 200

    found: list[dict[str, float]] = []
    for start in range(width * height):
        if labels[start] != -1 or background(rgb(start)):
            continue
        colour = rgb(start)
        stack, pixels = [start], []
        labels[start] = len(found)
        while stack:  # flood fill of one colour
            i = stack.pop()
            pixels.append(i)
            x, y = i % width, i // width
            for j in ((i - 1) if x > 0 else -1, (i + 1) if x < width - 1 else -1,
                      (i - width) if y > 0 else -1, (i + width) if y < height - 1 else -1):
                if j >= 0 and labels[j] == -1 and rgb(j) == colour:
                    labels[j] = len(found)
                    stack.append(j)
        if len(pixels) < 20:
            continue  # specks
        xs, ys = [i % width for i in pixels], [i // width for i in pixels]
        box = (max(xs) - min(xs) + 1) * (max(ys) - min(ys) + 1)
        fill = len(pixels) / box
        cx, cy = _to_table((max(xs) + min(xs) + 1) / 2, (max(ys) + min(ys) + 1) / 2)
        found.append({
            "x": round(cx, 2), "y": round(cy, 2), "size": round((max(xs) - min(xs) + 1) / WIDTH * 1.6 / 2, 3),
            "red": colour[0] / 255, "green": colour[1] / 255, "blue": colour[2] / 255, "fill": fill,
            # the outline's corners, as the pixels show them: a full box has 4, a triangle 3, a disc none
            "corners": 4 if fill > 0.9 else 3 if fill < 0.65 else 0,
        })
    return sorted(found, key=lambda r: (r["x"], r["y"]))


class ImageSegmenter(cast.UnmanagedComponent):
    """Keeps one ``SceneObject`` per region of colour in the camera's latest frame.

    Args: ``camera`` (the frame's entry id, default ``camera``), ``min_period_s``
    (frames closer together than this are skipped; default 0.5).
    """

    def configure(self, args: dict[str, Any]) -> None:
        """Where the frames are."""
        self.camera = str(args.get("camera", "camera"))
        self.ids: dict[tuple[float, float], str] = {}  # region centre -> entry id
        self.frames = 0

    def start(self) -> None:
        """Watch the camera entry: only its newest frame matters (delivery latest)."""
        self.on_change(cast.address_filter(self.camera, include_entry=True), self.frame, delivery="latest")

    def frame(self, change: cast.WorkingMemoryChange) -> None:
        """Segment a frame; add regions not seen before, take away those gone."""
        if change.operation is cast.Operation.DELETE:
            return
        image = change.entry(Image).value
        self.frames += 1
        seen = set()
        for region in regions(image):
            key = (region["x"], region["y"])
            seen.add(key)
            if key in self.ids:
                continue
            obj = SceneObject(label=f"region-{len(self.ids) + 1}", frame=self.frames, x=region["x"], y=region["y"],
                              size=region["size"], red=region["red"], green=region["green"], blue=region["blue"],
                              corners=int(region["corners"]), fill=region["fill"])
            self.ids[key] = self.new_id()
            self.add(self.ids[key], obj)
            print(f"frame {image.header.seq}: new region {obj.label} at x={obj.x:+.2f}, y={obj.y:.2f}", flush=True)
        for key in [k for k in self.ids if k not in seen]:
            self.delete_entry(self.ids.pop(key))


class AnswerAnnouncer(cast.UnmanagedComponent):
    """Writes each answered question as the ``std_msgs/String`` entry ``answers`` (the bridge publishes it)."""

    def start(self) -> None:
        """Watch the questions of the own SA."""
        self.on_change(cast.local_type_filter(Question, cast.Operation.OVERWRITE, include_entry=True), self.answered)
        self.written = False

    def answered(self, change: cast.WorkingMemoryChange) -> None:
        """One ROS message per answer."""
        question = change.entry(Question).value
        if not question.answered:
            return
        text = String(data=f"q{question.number} {question.text} -> {question.answer}")
        if self.written:
            self.overwrite("answers", text)
        else:
            self.add("answers", text)
            self.written = True

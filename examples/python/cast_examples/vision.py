"""The vision SA: an unmanaged segmenter and two managed recognisers.

The segmenter puts a ``SceneObject`` into the vision WM for each region it
finds, moves them now and then, and takes one away. The colour and shape
recognisers watch for new regions and propose a task for each; the vision task
manager decides which run (``fifo``, two at a time, a short queue: proposals
beyond it are rejected, and the recogniser proposes again a little later).
Both recognisers write the same entries, so every update is a locked
read-modify-write.
"""

from __future__ import annotations

import random
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from typing import Any

from castdemo.scene_pb2 import RecognitionRequest, SceneObject

import cast
from cast_examples.scene import TrueObject, features, make_scene, name_colour, name_shape

__all__ = ["ColourRecogniser", "Recogniser", "Segmenter", "ShapeRecogniser"]


class Segmenter(cast.UnmanagedComponent):
    """Finds regions of interest in a synthetic scene and keeps them up to date.

    Args: ``objects`` (how many, up to 8), ``rate_hz`` (frames per second),
    ``seed``, ``move_every`` (frames between moves), ``remove_at`` (frame at
    which one object is taken away; 0: never).
    """

    def configure(self, args: dict[str, Any]) -> None:
        """Read the scene's parameters."""
        self.scene = make_scene(int(args.get("objects", 6)), int(args.get("seed", 7)))
        self.period = 1.0 / float(args.get("rate_hz", 4))
        self.move_every = int(args.get("move_every", 6))
        self.remove_at = int(args.get("remove_at", 0))
        self.rng = random.Random(int(args.get("seed", 7)))
        self.ids: dict[str, str] = {}  # label -> entry id

    def _region(self, obj: TrueObject, frame: int) -> SceneObject:
        f = features(obj, self.rng)
        return SceneObject(label=obj.label, frame=frame, x=obj.x, y=obj.y, size=obj.size, red=f["red"],
                           green=f["green"], blue=f["blue"], corners=int(f["corners"]), fill=f["fill"])

    def run(self) -> None:
        """One frame per period: a new region, a move, or a removal."""
        frame = 0
        while not self.wait_for_stop(self.period):
            frame += 1
            unseen = [o for o in self.scene if o.label not in self.ids]
            if unseen:
                obj = unseen[0]
                entry_id = self.new_id()
                self.add(entry_id, self._region(obj, frame))
                self.ids[obj.label] = entry_id
                print(f"frame {frame}: new region {obj.label} at x={obj.x:+.2f}", flush=True)
            elif self.remove_at and frame == self.remove_at and len(self.ids) > 1:
                label = sorted(self.ids)[-1]
                self.delete_entry(self.ids.pop(label))
                self.scene = [o for o in self.scene if o.label != label]
                print(f"frame {frame}: {label} was taken off the table", flush=True)
            elif frame % self.move_every == 0 and self.ids:
                label = self.rng.choice(sorted(self.ids))
                self._move(label, frame)

    def _move(self, label: str, frame: int) -> None:
        obj = next(o for o in self.scene if o.label == label)
        obj.y = round(min(0.9, max(0.1, obj.y + self.rng.uniform(-0.1, 0.1))), 2)
        entry_id = self.ids[label]
        # The recognisers write this entry too: lock, read, change, write.
        with self.lock(entry_id, cast.LockMode.O, timeout=5):
            region = self.get(entry_id, SceneObject)
            region.y, region.frame = obj.y, frame
            self.overwrite(entry_id, region)
        print(f"frame {frame}: {label} moved to y={obj.y:.2f}", flush=True)


class Recogniser(cast.ManagedComponent):
    """Base of the recognisers: one task per new region, run by a small pool of workers.

    Args: ``work_ms`` (how long recognising takes), ``retry_ms`` (wait before
    proposing a rejected task again).
    """

    feature = ""

    def configure(self, args: dict[str, Any]) -> None:
        """Read timings."""
        self.work_s = float(args.get("work_ms", 300)) / 1000
        self.retry_s = float(args.get("retry_ms", 700)) / 1000
        self.pool = ThreadPoolExecutor(2, thread_name_prefix=f"{self.feature}-worker")
        self.done = 0

    def start(self) -> None:
        """Watch for new regions in the own SA, then take on those already there (a segmenter may be quicker)."""
        self.proposed: set[str] = set()
        self.mutex = threading.Lock()
        self.on_change(cast.local_type_filter(SceneObject, cast.Operation.ADD), self.new_region)
        for entry in self.get_all(SceneObject):
            if not self.known(entry.value):
                self.propose_once(entry.id)

    def known(self, region: SceneObject) -> bool:
        """Whether the region already has this recogniser's feature."""
        return bool(getattr(region, self.feature))

    def new_region(self, change: cast.WorkingMemoryChange) -> None:
        """Propose to recognise a new region."""
        self.propose_once(change.id)

    def propose_once(self, object_id: str) -> None:
        """Propose a region's first task (the watch and the start-up read may both see it)."""
        with self.mutex:
            if object_id in self.proposed:
                return
            self.proposed.add(object_id)
        self.propose(object_id)

    def propose(self, object_id: str) -> None:
        """Propose the task for one region."""
        if self.running:
            self.propose_task(f"{self.feature} {object_id.rsplit(':', 1)[-1]}",
                              RecognitionRequest(object_id=object_id, feature=self.feature))

    def task_adopted(self, task: cast.Task) -> None:
        """Recognise on a worker, so that two adopted tasks run at once."""
        self.pool.submit(self._work, task)

    def task_rejected(self, task: cast.Task) -> None:
        """The queue was full: try again a little later."""
        request = task.data(RecognitionRequest)
        if request is not None:
            timer = threading.Timer(self.retry_s, self.propose, args=(request.object_id,))
            timer.daemon = True
            timer.start()

    def _work(self, task: cast.Task) -> None:
        request = task.data(RecognitionRequest)
        assert request is not None
        started = time.monotonic()
        time.sleep(self.work_s)  # the expensive part, as far as the task manager knows
        try:
            with self.lock(request.object_id, cast.LockMode.O, timeout=5):
                region = self.get(request.object_id, SceneObject)
                name = self.recognise(region)
                self.overwrite(request.object_id, region)
        except cast.NotFoundError:
            self.task_complete(task, cast.TaskOutcome.ABANDONED, "the region is gone")
            return
        except cast.CastError as exc:
            self.task_complete(task, cast.TaskOutcome.FAILED, exc.message)
            return
        self.done += 1
        self.task_complete(task, cast.TaskOutcome.SUCCEEDED, name)
        print(f"{region.label} is {name} ({task.task_id}, {time.monotonic() - started:.1f} s)", flush=True)

    def recognise(self, region: SceneObject) -> str:
        """Fill in the feature; return its name."""
        raise NotImplementedError

    def stop(self) -> None:
        """Let running work finish."""
        self.pool.shutdown(wait=True, cancel_futures=True)


class ColourRecogniser(Recogniser):
    """Names the colour of each region."""

    feature = "colour"

    def recognise(self, region: SceneObject) -> str:
        """Nearest named colour to the region's mean RGB."""
        region.colour = name_colour(region.red, region.green, region.blue)
        return region.colour


class ShapeRecogniser(Recogniser):
    """Names the shape of each region."""

    feature = "shape"

    def recognise(self, region: SceneObject) -> str:
        """Best match of corners and fill."""
        region.shape = name_shape(region.corners, region.fill)
        return region.shape

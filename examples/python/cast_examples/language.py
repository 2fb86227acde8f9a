"""The language SA: answers questions about the scene by reading the vision WM.

Questions arrive as ``Question`` entries in the language WM (the coordinator
puts them there). For each, the answerer proposes a task with the question's
priority; the language task manager (``priority``, one at a time) decides the
order; the answer is written back into the same entry.
"""

from __future__ import annotations

import re
import threading
from typing import Any

from castdemo.scene_pb2 import Question, SceneObject

import cast

__all__ = ["Answerer", "answer"]

_NUMBERS = ["no", "one", "two", "three", "four", "five", "six", "seven", "eight"]


def _name(o: SceneObject) -> str:
    return f"the {o.colour or 'unrecognised'} {o.shape or 'thing'}"


def _find(objects: list[SceneObject], colour: str, shape: str) -> list[SceneObject]:
    return [o for o in objects if (not colour or o.colour == colour) and (not shape or o.shape == shape)]


def answer(text: str, objects: list[SceneObject]) -> str:
    """Answer one question from the regions the vision SA knows."""
    q = text.lower().strip(" ?")
    m = re.fullmatch(r"what is (left|right) of the (\w+) (\w+)", q)
    if m:
        side, colour, shape = m.groups()
        anchors = _find(objects, colour, shape)
        if not anchors:
            return f"I see no {colour} {shape}"
        a = anchors[0]
        beside = [o for o in objects if (o.x < a.x if side == "left" else o.x > a.x) and o is not a]
        if not beside:
            return f"nothing is {side} of the {colour} {shape}"
        nearest = min(beside, key=lambda o: abs(o.x - a.x))
        return f"{_name(nearest)} is just {side} of the {colour} {shape}"
    m = re.fullmatch(r"what colou?r is the (\w+)", q)
    if m:
        found = _find(objects, "", m.group(1))
        if not found:
            return f"I see no {m.group(1)}"
        return " and ".join(sorted({o.colour or "unknown" for o in found})) if len(found) > 1 else found[0].colour
    m = re.fullmatch(r"how many (\w+?)s? are there", q)
    if m:
        what = m.group(1)
        n = len(objects) if what in ("object", "thing") else len(_find(objects, "", what))
        noun = "objects" if what in ("object", "thing") else f"{what}s"
        return f"{_NUMBERS[n] if n < len(_NUMBERS) else n} {noun if n != 1 else noun[:-1]}"
    m = re.fullmatch(r"is there an? (\w+) (\w+)", q)
    if m:
        found = _find(objects, m.group(1), m.group(2))
        return "yes" if found else "no"
    m = re.fullmatch(r"where is the (\w+) (\w+)", q)
    if m:
        found = _find(objects, m.group(1), m.group(2))
        if not found:
            return f"I see no {m.group(1)} {m.group(2)}"
        o = found[0]
        side = "left" if o.x < -0.1 else "right" if o.x > 0.1 else "middle"
        return f"on the {side}, {o.y:.2f} m away"
    return "I do not understand the question"


class Answerer(cast.ManagedComponent):
    """Answers ``Question`` entries of its SA. Args: ``vision_sa`` (where the scene is)."""

    def configure(self, args: dict[str, Any]) -> None:
        """Where to look."""
        self.vision_sa = str(args.get("vision_sa", "vision"))
        self.pending: dict[str, str] = {}  # task id -> question id

    def start(self) -> None:
        """Watch for new questions, then take on those already asked."""
        self.seen: set[str] = set()
        self.mutex = threading.Lock()
        self.on_change(cast.local_type_filter(Question, cast.Operation.ADD), self.asked)
        for entry in self.get_all(Question):
            if not entry.value.answered:
                self.take(entry.id, entry.value)

    def asked(self, change: cast.WorkingMemoryChange) -> None:
        """Propose to answer, at the question's priority."""
        self.take(change.id, self.get(change.id, Question))

    def take(self, question_id: str, question: Question) -> None:
        """Propose to answer one question, once."""
        with self.mutex:
            if question_id in self.seen:
                return
            self.seen.add(question_id)
            task = self.propose_task(f"answer q{question.number}", priority=question.priority)
            self.pending[task.task_id] = question_id

    def task_adopted(self, task: cast.Task) -> None:
        """Read the scene, answer, write the answer into the question."""
        with self.mutex:  # take() records the task under the mutex, maybe after the decision came
            question_id = self.pending.pop(task.task_id)
        objects = [e.value for e in self.get_all(SceneObject, subarchitecture=self.vision_sa)]
        with self.lock(question_id, cast.LockMode.OD, timeout=5):
            question = self.get(question_id, Question)
            question.answer, question.answered = answer(question.text, objects), True
            self.overwrite(question_id, question)
        self.task_complete(task, cast.TaskOutcome.SUCCEEDED)

    def task_rejected(self, task: cast.Task) -> None:
        """Not expected under the demo's policy; say so."""
        print(f"could not answer ({task.reason})", flush=True)

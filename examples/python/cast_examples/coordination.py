"""The coordination SA: a privileged coordinator that posts goals into the other SAs.

It asks a script of questions by writing ``Question`` entries straight into
the language WM (a cross-SA write only a privileged component may make), and
prints each answer when the language SA writes it back. It reports how the
conversation went as outcomes an experiment measures (docs/experiments.md):
``questions_answered`` (1 per answer) and ``answer_time_s`` (from asking to
the answer).
"""

from __future__ import annotations

import threading
import time
from typing import Any

from castdemo.scene_pb2 import Question

import cast

__all__ = ["Coordinator"]


class Coordinator(cast.UnmanagedComponent):
    """Asks scripted questions. Args: ``questions``, ``language_sa``, ``start_after_s``, ``every_s``, ``urgent``.

    ``start_after_s`` only paces the demo (the scene fills before the first question): that the
    answerer's watch is in place before the first question comes from the start barrier.
    """

    def configure(self, args: dict[str, Any]) -> None:
        """Read the script."""
        self.questions = [str(q) for q in args.get("questions", [])]
        self.language_sa = str(args.get("language_sa", "language"))
        self.start_after = float(args.get("start_after_s", 3.0))
        self.every = float(args.get("every_s", 1.5))
        self.urgent = {str(q) for q in args.get("urgent", [])}
        self.answered = 0
        self.asked: dict[int, float] = {}  # question number -> when it was asked (monotonic), until answered
        self.mutex = threading.Lock()

    def start(self) -> None:
        """Listen for answers in the language WM."""
        self.on_change(
            cast.ChangeFilter(operations=frozenset({cast.Operation.OVERWRITE}), type=Question.DESCRIPTOR.full_name,
                              subarchitecture=self.language_sa),
            self.replied,
        )

    def run(self) -> None:
        """Ask one question every few seconds."""
        if self.wait_for_stop(self.start_after):
            return
        for number, text in enumerate(self.questions, 1):
            priority = 10 if text in self.urgent else 0
            question = Question(number=number, text=text, asked_by=self.component_id, priority=priority)
            with self.mutex:  # before the add: the answer may come before add() returns
                self.asked[number] = time.monotonic()
            self.add(f"question-{number}", question, subarchitecture=self.language_sa)
            self.say(f"asks q{number}{' (urgent)' if priority else ''}: {text}")
            if self.wait_for_stop(self.every):
                return
        self.wait_for_stop()

    def replied(self, change: cast.WorkingMemoryChange) -> None:
        """Print an answer and report it."""
        question = self.get(change.id, Question, subarchitecture=self.language_sa)
        if question.answered:
            with self.mutex:
                self.answered += 1
                asked = self.asked.pop(question.number, None)
            self.say(f"q{question.number} {question.text} -> {question.answer}")
            if asked is not None:  # once per question, whatever else overwrites its entry
                self.report("questions_answered", 1)
                self.report("answer_time_s", time.monotonic() - asked)

    def say(self, line: str) -> None:
        """Print one line of the conversation.

        The asking thread and the answer callback both print: ``print`` writes the text and its
        newline in two calls, so without the lock one line could land inside the other.
        """
        with self.mutex:
            print(line, flush=True)

    def stop(self) -> None:
        """Say how the conversation went."""
        print(f"{self.answered} of {len(self.questions)} questions answered", flush=True)

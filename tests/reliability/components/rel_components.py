"""Components of the reliability tests (put on PYTHONPATH through a configuration's python_path)."""

from __future__ import annotations

from google.protobuf.wrappers_pb2 import Int64Value, StringValue

import cast


class Ticker(cast.UnmanagedComponent):
    """Overwrites ``tick`` every 0.1 s; the first failure is written to ``tick-error`` (if it still can)."""

    def run(self) -> None:
        self.add("tick", Int64Value(value=0))
        i = 0
        while not self.wait_for_stop(0.1):
            i += 1
            try:
                self.overwrite("tick", Int64Value(value=i))
            except cast.CastError as exc:
                self.log.error("tick %d failed: %s", i, exc)
                try:
                    self.add("tick-error", StringValue(value=f"{exc.code}: {exc.message}"))
                except cast.CastError:
                    pass
                return

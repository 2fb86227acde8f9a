"""The Python half of the Node example: it answers every greeting another component adds to its SA.

The Node component (component.js) adds ``google.protobuf.StringValue`` entries
and watches that type in its SA, so it prints the replies written here: data
crossing languages both ways through one working memory.
"""

from google.protobuf.wrappers_pb2 import StringValue

import cast


class Reactor(cast.UnmanagedComponent):
    """Replies to each StringValue added by another component with a StringValue ``reply-<id>``."""

    def start(self) -> None:
        """Watch additions of StringValue entries in the own SA."""
        self.on_change(cast.local_type_filter(StringValue, cast.Operation.ADD), self.greeted)

    def greeted(self, change: cast.WorkingMemoryChange) -> None:
        """Answer a greeting (but not our own replies)."""
        if change.source_component == self.component_id:
            return
        text = self.get(change.id, StringValue).value
        print(f"python read {change.id} by {change.source_component}: {text!r}", flush=True)
        self.add(f"reply-{change.id}", StringValue(value=f"python read {text!r}"))

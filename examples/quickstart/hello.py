"""The quick-start component: writes three greetings and prints every change it sees."""

from google.protobuf.wrappers_pb2 import StringValue

import cast


class Hello(cast.UnmanagedComponent):
    """Adds greetings to its own working memory and watches them arrive."""

    def start(self) -> None:
        self.seen = 0
        self.on_change(cast.local_type_filter(StringValue), self.changed)

    def changed(self, change: cast.WorkingMemoryChange) -> None:
        text = self.get(change.id, StringValue).value
        print(f"{change.operation.name} {change.id} (revision {change.revision}): {text}", flush=True)
        self.seen += 1
        if self.seen == 3:
            self.request_stop()

    def run(self) -> None:
        for i in range(3):
            self.add(self.new_id(), StringValue(value=f"hello {i}"))
        self.wait_for_stop()

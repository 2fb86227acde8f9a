"""The live view: a running system's working memories served to the Foxglove app (docs/foxglove.md).

``cast foxglove`` and ``cast run --foxglove`` serve the Foxglove WebSocket
protocol through the ``foxglove-sdk`` package. The channels and messages are
those of a recording (:mod:`cast.recording.channels`), fed by the recorder's
resuming watch loop (:class:`cast.recording.recorder.Recorder`), so a live
view and an MCAP file of the same system show the same topics and schemas.
Beside the recorder in the layering: the client library and the recording
package only, never the server, the orchestrator or the command line.
"""

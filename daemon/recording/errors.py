"""The error every reader of recordings raises for a file it cannot read."""


class RecordingError(Exception):
    """A file cannot be read as a loopcal recording; the message names the file and why."""


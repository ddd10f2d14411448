"""The error every reader of recordings raises for a file it cannot read."""


class RecordingError(Exception):
    """A file cannot be read as a loopcal recording; the message names the file and why.

    Raised by :func:`~loopcal.daemon.recording.reader.read_recordings`,
    :func:`~loopcal.daemon.recording.names.find_recordings` and the other readers for a
    path that names no recording: missing, unreadable, not a regular file, not MCAP at
    all, an MCAP file of something else, or a recording of another format version. A
    damaged recording is no error: it is read as far as it checks out, and the damage is
    reported (:class:`~loopcal.daemon.recording.recordingfile.RecordingFile`).
    """


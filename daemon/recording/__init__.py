"""The recording format: MCAP files of raw scans, derived plate poses and events.

One recording file holds, for a stretch of time (see docs/recording.md for the full table):

========================  ==========================================  =========  ===============
topic                     schema                                      encoding   rate
========================  ==========================================  =========  ===============
``/daq/scans``            ``loopcal_msgs/msg/ScanBlock`` (ros2msg)    cdr        one per flush
``/loopcal/events``       ``loopcal.Event`` (jsonschema)              json       when it happens
``/loopcal/log``          ``foxglove.Log`` (jsonschema)               json       when it happens
``/joint/state``          ``loopcal_msgs/msg/JointState``             cdr        every scan
``/plate/transform``      ``foxglove_msgs/msg/FrameTransform``        cdr        every good scan
``/plate/scene``          ``foxglove.SceneUpdate`` (jsonschema)       json       once per file
========================  ==========================================  =========  ===============

plus metadata records ``loopcal`` (version, host, command), ``device`` (what the DAQ said it
is) and ``controller_config`` (the parameters the poses were computed with).

``/daq/scans`` is the record: every scan exactly once, raw and lossless, in blocks of at most
one flush period (about one second). The other channels are views for people: Foxglove plots
``/joint/state`` (volts and lengths of every channel) at the full scan rate and its 3D panel
moves the plate frame of ``/plate/transform``.

Layout, chosen for crash safety and for fast reading: every flush (about once per second)
writes two chunks, first the raw block with any events, then the per-scan views, and fsyncs.
A reader that only wants the scans skips the view chunks by the chunk index, and decodes each
block with one ``numpy.frombuffer``: the block's CDR body is the rows of
:data:`loopcal.daemon.scan_rows.SCAN_DTYPE` back to back. A file cut short by a crash or a power
loss
still reads back up to its last complete chunk.

The modules, bottom up: :mod:`~loopcal.daemon.recording.schemas` (topics, channels, schemas),
:mod:`~loopcal.daemon.recording.cdr` (message layouts, scan blocks),
:mod:`~loopcal.daemon.recording.views` (per-scan poses for people),
:mod:`~loopcal.daemon.recording.names` (file names), :mod:`~loopcal.daemon.recording.writer`
(:class:`RecordingWriter`); the one parser of MCAP records, which the reader, ``loopcal
verify`` and the compaction share: :mod:`~loopcal.daemon.recording.damage` (what could not be
trusted), :mod:`~loopcal.daemon.recording.mcap_records` (records checked before they are trusted,
chunks, indexes, resynchronisation), :mod:`~loopcal.daemon.recording.mcap_summary` (the summary
section, by its CRC) and :mod:`~loopcal.daemon.recording.walk` (the data section record by
record); then :mod:`~loopcal.daemon.recording.filereader` (one file, and what it lost:
:mod:`~loopcal.daemon.recording.recordingfile`), :mod:`~loopcal.daemon.recording.reader`
(:func:`read_recordings`), :mod:`~loopcal.daemon.recording.verify` (every record checked:
:mod:`~loopcal.daemon.recording.verify_chunks`,
:mod:`~loopcal.daemon.recording.verify_summary`) and
:mod:`~loopcal.daemon.recording.compact` (closed files rewritten in chunks of a minute). Used
by the recorder, the worker, replay and the inspection tools.

Imports: calibration/ (kinematics for the views), mcap, numpy, and the base modules of
:mod:`loopcal.daemon` (scans, events, version). Nothing else of daemon/.
"""

import lazy_loader as lazy

# Loaded on first use (PEP 562, by lazy_loader), as calibration/ and drivers/ are: a module
# that needs only the file names (``loopcal.daemon.recording.names``) or the schemas' topics,
# and a command's ``--help``, do not pay for numpy and mcap.
_SUBMODULES = ("cdr", "errors", "losses", "names", "reader", "recordingfile", "schemas", "views",
               "writer")  # fmt: skip
__getattr__, __dir__, _names = lazy.attach(
    __name__,
    submodules=_SUBMODULES,
    submod_attrs={
        "cdr": ["FRAME_TRANSFORM_DTYPE", "JOINT_STATE_DTYPE", "cdr_dtype", "cdr_messages",
                "decode_scan_blocks", "decode_scan_blocks_checked", "encode_scan_block"],
        "errors": ["RecordingError"],
        "losses": ["Loss"],
        "names": ["find_recordings", "name_time_ns", "recording_name"],
        "reader": ["Recording", "message_time_range", "read_recordings"],
        "recordingfile": ["RecordingFile"],
        "schemas": ["BASE_FRAME", "BLOCK_SPAN_NS", "CHANNELS", "COMPACT_FORMAT",
                    "FORMAT_VERSION", "FRAME_TRANSFORM_SCHEMA", "JOINT_STATE_SCHEMA",
                    "JSON_SCHEMAS", "PLATE_FRAME", "READ_FORMATS", "SCAN_BLOCK_SCHEMA",
                    "SCAN_COLUMNS_SCHEMA", "TOPIC_EVENTS", "TOPIC_LOG", "TOPIC_SCANS",
                    "TOPIC_SCENE", "TOPIC_STATE", "TOPIC_TRANSFORM", "scan_block_msgdef"],
        "views": ["JointStates", "joint_states", "state_messages", "transform_messages"],
        "writer": ["RecordingWriter", "metadata_records"],
    },
)  # fmt: skip
#: the names above (``from loopcal.daemon.recording import *``), without the submodules
__all__ = [name for name in _names if name not in _SUBMODULES]

"""Tests of daemon/recording/: the format, damage, compaction, Foxglove's reader."""

"""Tests of the project as a whole: packaging, API reference, Foxglove layout, alert rules."""

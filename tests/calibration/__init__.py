"""Tests of calibration/: the mathematics, against independent references and properties."""

"""Tests of daemon/config/: the controller's config."""

"""The version of loopcal that runs (recorded in every file and every calibration)."""

from __future__ import annotations

import functools
from importlib import metadata as importlib_metadata


@functools.cache  # the version of the code that runs; reading the metadata takes 1 ms
def loopcal_version() -> str:
    try:
        return importlib_metadata.version("loopcal")
    except importlib_metadata.PackageNotFoundError:  # running from a bare checkout
        return "0+unknown"

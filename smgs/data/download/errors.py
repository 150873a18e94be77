"""The download's errors: each message says what happened and what to do next."""

from __future__ import annotations


class DownloadError(RuntimeError):
    """A dataset could not be fetched, checked or unpacked; nothing was put under a final name."""


class NetworkError(DownloadError):
    """The server could not be reached or the transfer broke off (a rerun resumes)."""


class RemoteChangedError(DownloadError):
    """The server answers with an error (404, ...) or offers another file than the one recorded."""


class ArchiveError(DownloadError):
    """The archive is not a valid zip, lacks a scene, or a scene in it is incomplete."""


class DiskSpaceError(DownloadError):
    """Not enough free space for the archive and the scenes unpacked from it."""

"""``smgs download``: the paper's datasets from the archives their authors publish, resumed after an
interruption, checked, and unpacked into the layout configs/dataset/*.yaml read (docs/usage.md,
"Downloading the datasets").

- ``sources``: the archives, their scenes, image counts and terms (the facts, with their sources);
- ``fetch``: one archive over HTTP into a partial file, with HTTP Range resume and a progress bar;
- ``unpack``: zip checks, extraction into a temporary folder, the scene check, the rename into place;
- ``manifest``: ``<data root>/smgs-downloads.json``, what was downloaded (URL, size, sha256, date);
- ``get``: the order of it all (``download``).
"""

from smgs.data.download.errors import (ArchiveError, DiskSpaceError, DownloadError, NetworkError,
                                       RemoteChangedError)
from smgs.data.download.get import (DownloadRequest, DownloadResult, datasets_of_archive, download,
                                    download_command)
from smgs.data.download.manifest import MANIFEST
from smgs.data.download.sources import SOURCES, Archive, DatasetSource, get_source

__all__ = ["download", "download_command", "DownloadRequest", "DownloadResult", "datasets_of_archive", "MANIFEST",
           "SOURCES",
           "Archive", "DatasetSource", "get_source", "DownloadError", "NetworkError", "RemoteChangedError",
           "ArchiveError", "DiskSpaceError"]

"""What goes wrong with a scene's files, as exceptions: a module that imports nothing, so that the
modules that only name them (the dataset layouts, the image reader, the download) stay light."""


class DatasetNotFoundError(FileNotFoundError):
    """A scene or dataset folder is absent (a run with ``on_missing=skip`` may skip the cell)."""


class SceneFormatError(ValueError):
    """A scene exists but cannot be used as it is: a corrupt or incomplete model, an unsupported
    camera, inconsistent image sizes. The message names the file and the fix."""


class MissingImageError(FileNotFoundError):
    """An image the camera model lists is not on disk (a broken scene, never skipped silently)."""


class SceneContractError(SceneFormatError):
    """A scene a format made breaks the scene contract (``smgs.data.contract``); the message names
    the scene, the view and the rule, and the fix."""

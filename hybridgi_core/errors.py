"""Named errors of the core; the add-on turns them into one UI report."""


class HybridGIError(Exception):
    """Base class of every error the core raises on purpose."""


class EmptySceneError(HybridGIError):
    """The scene holds no triangle that can be traced."""


class InvalidGeometryError(HybridGIError):
    """Geometry arrays have wrong shapes, dtypes or non-finite values that cannot be dropped."""


class SettingsError(HybridGIError, ValueError):
    """A setting is not finite or out of its documented range (also a ValueError)."""


class LimitError(HybridGIError):
    """A size limit (cache memory, GPU texture size, texture resolution) would be exceeded; the
    message names the limit and the setting to change. Raised before the allocation."""

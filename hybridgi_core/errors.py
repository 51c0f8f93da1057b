"""Named errors of the core; the add-on turns them into one UI report."""


class HybridGIError(Exception):
    """Base class of every error the core raises on purpose."""


class EmptySceneError(HybridGIError):
    """The scene holds no triangle that can be traced."""


class InvalidGeometryError(HybridGIError):
    """Geometry arrays have wrong shapes, dtypes or non-finite values that cannot be dropped."""


class SettingsError(HybridGIError):
    """A setting is out of its documented range."""

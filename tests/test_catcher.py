"""Shadow catchers' composition (`hybridgi_core/catcher.py`), without Blender."""

from types import SimpleNamespace

import numpy as np

from hybridgi_core.catcher import CatcherPixels, compose, light_ratio, open_irradiance
from hybridgi_core.snapshot import World


def _pixels(n):
    return CatcherPixels(np.arange(n), np.zeros((n, 3), np.float32), np.tile([0.0, 0.0, 1.0], (n, 1)).astype(np.float32))


def test_open_irradiance_of_a_uniform_world_is_pi_times_its_colour():
    world = World(color=np.array([0.2, 0.4, 0.6], np.float32))
    np.testing.assert_allclose(open_irradiance(world, np.array([[0.0, 0.0, 1.0]])), [[0.2 * np.pi, 0.4 * np.pi,
                                                                                       0.6 * np.pi]], rtol=1e-6)


class _Lamps:
    """A system whose one lamp gives 2 W/m^2 unshadowed per channel (`GISystem.direct`'s output)."""

    def __init__(self):
        self.scene = SimpleNamespace(lights=[object()], world=World(color=np.array([0.1, 0.1, 0.1], np.float32)))

    def direct(self, points, normals, frame, samples=None, unshadowed=None):
        unshadowed[:] = 2.0
        return np.zeros((points.shape[0], 3), np.float32)


def test_the_ratio_is_the_light_with_the_scene_over_the_lamps_unshadowed_and_the_open_sky():
    system = _Lamps()
    free = 2.0 + 0.1 * np.pi
    light = np.array([[free, free, free], [0.5 * free, 0.25 * free, 0.0], [1.2 * free] * 3], np.float32)
    ratio = light_ratio(system, _pixels(3), light, frame=0)
    np.testing.assert_allclose(ratio, [[1, 1, 1], [0.5, 0.25, 0.0], [1.2, 1.2, 1.2]], rtol=1e-5)


def test_no_light_at_all_keeps_the_world_behind_as_it_is():
    system = SimpleNamespace(scene=SimpleNamespace(lights=[], world=World()))
    np.testing.assert_allclose(light_ratio(system, _pixels(2), np.zeros((2, 3), np.float32), frame=0), 1.0)


def test_compose_writes_the_world_times_the_ratio_or_the_shadow_as_alpha():
    combined = np.full((2, 2, 4), 0.7, np.float32)
    ratio = np.array([[0.5, 0.5, 0.5]], np.float32)
    compose(combined, np.array([3]), ratio, np.array([[0.2, 0.4, 0.8]], np.float32), transparent=False)
    np.testing.assert_allclose(combined[1, 1], [0.1, 0.2, 0.4, 1.0])
    np.testing.assert_allclose(combined[0, 0], [0.7] * 4)  # other pixels untouched
    compose(combined, np.array([0]), ratio, None, transparent=True)
    np.testing.assert_allclose(combined[0, 0], [0.0, 0.0, 0.0, 0.5])

"""A scene whose placed instances would not fit in memory is refused before they are copied, with
a message naming the triangle count and what to change (`sync.check_flattened_size`): HybridGI
copies every instance into one mesh, and a large scatter was killed by the system part way."""

from __future__ import annotations

import pytest


@pytest.mark.blender
def test_the_budget_counts_placed_triangles_against_the_memory_available(sync):
    sync.check_flattened_size(1_000_000, available=10 * 2**30)  # 0.2 GB of 10 GB: fine
    with pytest.raises(sync.LimitError, match=r"50,000,000 triangles.*instance"):
        sync.check_flattened_size(50_000_000, available=8 * 2**30)  # 10 GB of 8 GB


@pytest.mark.blender
def test_a_scatter_too_large_for_memory_is_refused_by_the_sync(bpy_module, empty_scene, sync, monkeypatch):
    """Two hundred linked copies of a 1280-triangle sphere (256k triangles placed) with 40 MB
    free: the sync raises LimitError naming the count, before placing them; with 4 GB it syncs."""
    bpy, scene = bpy_module, empty_scene
    bpy.ops.mesh.primitive_ico_sphere_add(subdivisions=4)
    source = bpy.context.object
    for i in range(199):
        copy = bpy.data.objects.new(f"copy{i}", source.data)
        copy.location = (3.0 * (i % 20), 3.0 * (i // 20), 0.0)
        scene.collection.objects.link(copy)
    depsgraph = bpy.context.evaluated_depsgraph_get()
    monkeypatch.setattr(sync, "available_memory", lambda: 40 * 2**20)
    with pytest.raises(sync.LimitError, match=r"256,000 triangles"):
        sync.snapshot_from_depsgraph(depsgraph)
    monkeypatch.setattr(sync, "available_memory", lambda: 4 * 2**30)
    assert sync.snapshot_from_depsgraph(depsgraph).geometry.triangle_count == 256_000

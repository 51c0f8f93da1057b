"""The `hybridgi` command: headless renders through the bpy module."""

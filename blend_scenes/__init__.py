"""HybridGI's own test scenes: bpy-free descriptions (`procedural`) and their .blend builder (`build`)."""

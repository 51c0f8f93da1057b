/* G-buffer: world-space geometry in, world-space attributes out (no model matrix: the snapshot
 * is already in world space). */
void main()
{
  world_pos = pos;
  world_nor = nor;
  tex_uv = uv;
  map_uv = nuv;
  uv_ok = uv_valid;
  world_tan = tangent;
  gl_Position = camera.view_proj * vec4(pos, 1.0);
}

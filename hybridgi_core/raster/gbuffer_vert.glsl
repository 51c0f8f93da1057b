/* G-buffer: world-space geometry in, world-space attributes out (no model matrix: the snapshot
 * is already in world space). PLAIN_LAYOUT (`GBufferPass`'s "plain" vertex layout, scenes without
 * normal maps): no tangent or map-UV attributes; the frame is zero (the fragment shader keeps the
 * smooth normal) and the maps' UVs are the texture UVs, as the full layout's zeros and copies give. */
void main()
{
  world_pos = pos;
  world_nor = nor;
  tex_uv = uv;
  uv_ok = uv_valid;
#ifdef PLAIN_LAYOUT
  map_uv = uv;
  world_tan = vec4(0.0);
#else
  map_uv = nuv;
  world_tan = tangent;
#endif
  gl_Position = camera.view_proj * vec4(pos, 1.0);
}

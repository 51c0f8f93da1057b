/* G-buffer of a scene without normal or bump maps (`GBufferPass` layout "plain"): no tangent or
 * map-UV attributes in its vertices, the frame zero (the shader keeps the smooth normal) and the
 * maps' UVs the texture UVs, as gbuffer_vert.glsl reads them from zeros and copies there. */
void main()
{
  world_pos = pos;
  world_nor = nor;
  tex_uv = uv;
  map_uv = uv;
  uv_ok = uv_valid;
  world_tan = vec4(0.0);
  gl_Position = camera.view_proj * vec4(pos, 1.0);
}

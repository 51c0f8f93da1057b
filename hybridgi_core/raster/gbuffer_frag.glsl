/* G-buffer MRT. One draw per material: the material's constants are push constants and its
 * texture (or a 1x1 dummy) is `albedo_tx`. */

ivec2 wrap_texel(ivec2 i, ivec2 n)
{
  /* GLSL leaves integer % of negative operands undefined; float mod() floors. */
  return ivec2(mod(vec2(i), vec2(n)));
}

/* Bilinear filtering with REPEAT done by hand, texel centres at (i + 0.5) / size as in Cycles'
 * Linear interpolation: independent of the sampler state the Python API can set. */
vec3 sample_repeat_bilinear(vec2 uv)
{
  ivec2 size = textureSize(albedo_tx, 0);
  vec2 st = uv * vec2(size) - 0.5;
  vec2 f = floor(st);
  vec2 t = st - f;
  ivec2 i0 = ivec2(f);
  vec3 c00 = texelFetch(albedo_tx, wrap_texel(i0, size), 0).rgb;
  vec3 c10 = texelFetch(albedo_tx, wrap_texel(i0 + ivec2(1, 0), size), 0).rgb;
  vec3 c01 = texelFetch(albedo_tx, wrap_texel(i0 + ivec2(0, 1), size), 0).rgb;
  vec3 c11 = texelFetch(albedo_tx, wrap_texel(i0 + ivec2(1, 1), size), 0).rgb;
  return mix(mix(c00, c10, t.x), mix(c01, c11, t.x), t.y);
}

void main()
{
  vec3 n = normalize(world_nor);
  /* Cycles flips the shading normal of back faces so it faces the camera. */
  if (!gl_FrontFacing) {
    n = -n;
  }
  vec3 albedo = fallback_albedo.rgb;
  /* uv_ok interpolates to < 1 on triangles with any NaN-UV corner: no usable UV there. */
  if (has_texture != 0 && uv_ok > 0.999) {
    albedo = base_color.rgb * sample_repeat_bilinear(tex_uv);
  }
  out_albedo = vec4(albedo, 1.0);
  out_normal = vec4(n, 1.0);
  out_position = vec4(world_pos, 1.0);
  out_emission = vec4(emission.rgb, 1.0);
  out_depth = view_depth(camera.view_z, world_pos);
}

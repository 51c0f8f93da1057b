/* Deferred shading at full resolution (seed step 9), with the vertical bilateral taps fused in.
 *
 * Irradiances E (W/m^2): E_direct from lamps (CPU shadow rays, full res), E_cache_direct (sky +
 * emissive surfaces from the cache) and E_indirect (bounced light from the cache), all upsampled
 * here except E_direct. Cycles' passes: Diffuse Direct/Indirect = E / pi, Combined = albedo x
 * (all E) / pi + emission.
 *
 * AO: the AO pass is the MIN/MUL blend of ray AO (cache) and screen-space AO. The cache's
 * irradiance already carries the ray-scale occlusion (its probe rays return the occluders'
 * radiance, not the sky's), so only the occlusion the blend ADDS to ray AO is applied to it:
 *   factor = blend(ray_ao, ss_ao) / ray_ao  ->  MUL: ss_ao;  MIN: min(1, ss_ao / ray_ao).
 * The light the near-field occluders reflect (SSAO bounce) is then added to E_indirect. */

#define BLEND_MUL 0
#define BLEND_MIN 1

/* The world map's radiance towards this pixel (world_background.py): the view direction through
 * the projection the G-buffer was drawn with, in Blender's equirectangular layout
 * (u = (pi - atan2(y, x)) / 2pi, v = 0.5 + asin(z) / pi), past the texture's wrap column. */
vec3 world_background()
{
  vec2 ndc = gl_FragCoord.xy / vec2(textureSize(full_position_tx, 0)) * 2.0 - 1.0;
  vec4 a = world.inv_view_proj * vec4(ndc, -1.0, 1.0);
  vec4 b = world.inv_view_proj * vec4(ndc, 1.0, 1.0);
  vec3 d = (world.texture_from_world * vec4(b.xyz / b.w - a.xyz / a.w, 0.0)).xyz;
  d /= max(length(d), 1e-30);
  float u = (M_PI - atan(d.y, d.x)) / (2.0 * M_PI);
  float v = 0.5 + asin(clamp(d.z, -1.0, 1.0)) / M_PI;
  float width = world.params.y;
  return texture(world_tx, vec2((u * (width - 2.0) + 1.0) / width, v)).rgb * world.params.x;
}

void main()
{
  ivec2 px = ivec2(gl_FragCoord.xy);
  vec4 P = texelFetch(full_position_tx, px, 0);
  if (P.w < 0.5) {
    /* Background: the world's radiance in Combined (alpha 0, as a transparent film would). */
    out_combined = vec4((has_world_map != 0) ? world_background() : world_color.rgb, 0.0);
    out_diffuse_direct = vec4(0.0);
    out_diffuse_indirect = vec4(0.0);
    out_diffuse_color = vec4(0.0);
    out_ao = 0.0;
    return;
  }
  vec3 albedo = texelFetch(albedo_tx, px, 0).rgb;
  vec3 np = texelFetch(full_normal_tx, px, 0).xyz;
  float zp = texelFetch(full_depth_tx, px, 0).r;
  vec3 emission = texelFetch(emission_tx, px, 0).rgb;
  vec3 e_lamps = texelFetch(direct_tx, px, 0).rgb;

  vec4 gi_indirect, gi_direct, ssao;
  bilateral_vertical(px, P.xyz, np, zp, gi_indirect, gi_direct, ssao);

  float ray_ao = clamp(gi_indirect.a, 0.0, 1.0);
  float ss_ao = clamp(ssao.a, 0.0, 1.0);
  float ao;
  float cache_factor;
  if (blend_mode == BLEND_MIN) {
    ao = min(ray_ao, ss_ao);
    cache_factor = (ray_ao > 1e-4) ? min(1.0, ss_ao / ray_ao) : 1.0;
  }
  else {
    ao = ray_ao * ss_ao;
    cache_factor = ss_ao;
  }

  vec3 bounce = ssao.rgb;
  if (relative_bounce != 0) {
    /* SSAO ran without an irradiance texture: its bounce is an albedo-weighted occluded share;
     * the occluders (within the AO radius) are taken to receive what this point receives. */
    bounce *= e_lamps + gi_direct.rgb + gi_indirect.rgb;
  }
  vec3 e_direct = e_lamps + gi_direct.rgb * cache_factor;
  vec3 e_indirect = gi_indirect.rgb * cache_factor + bounce;

  out_diffuse_direct = vec4(e_direct / M_PI, 1.0);
  out_diffuse_indirect = vec4(e_indirect / M_PI, 1.0);
  out_diffuse_color = vec4(albedo, 1.0);
  out_ao = ao;

  vec3 color = albedo * (e_direct + e_indirect) / M_PI + emission;
  if (has_glossy != 0) {
    color += texelFetch(glossy_tx, px, 0).rgb; /* the lamps' glossy reflection (CPU, glossy.py) */
  }
  if (debug_view == 1) {
    color = albedo * e_indirect / M_PI;
  }
  else if (debug_view == 2) {
    color = vec3(ao);
  }
  else if (debug_view == 3) {
    color = vec3((px.x < textureSize(full_position_tx, 0).x / 2) ? ray_ao : ss_ao);
  }
  out_combined = vec4(color, 1.0);
}

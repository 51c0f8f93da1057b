/* `pixel_gather.upsample_full` at one full-res pixel (see upsample.py): the 3 x 3 GI pixels
 * around it, each weighted by a Gaussian of its sample pixel's distance (inv2s2), the range
 * weight exp(-(plane distance / (plane_sigma x view distance))^2) x max(0, n . n_q)^normal_power,
 * its validity and the stretch term (stretch > 0, `pixel_gather._stretch_into`); sums of the
 * cache's irradiance (7), the filtered residual (7), its luminance, luminance^2 and AO^2. Where a
 * tap's normal differs from the pixel's (cos < FLAT_COS) the cache's part is the taps' SH
 * evaluated at the pixel's own normal (`sh_irradiance_weight`, common_lib.glsl).
 *
 * pts / nrm : the full-res pixels' position (w = 1 on geometry) and unit normal; rec_pos : GI
 * position, validity; rec_nrm : GI normal, residual luminance; rec_xy : sample pixel x, y,
 * luminance^2, AO^2; cache_a / cache_b, res_a / res_b : channels 0-3 / 4-6; sh : the GI pixels'
 * radiance SH, coefficient k of GI pixel (i, j) at texels (2 i, j K + k) (channels 0-3) and
 * (2 i + 1, j K + k) (4-6).
 *
 * Out: cache_a, (cache 4-6, best range weight), res_a, (res 4-6, cover), (spread of the
 * luminance, spread of the AO, turned, 1). */

const float FLAT_COS = 0.99;

void main()
{
  ivec2 p = ivec2(gl_FragCoord.xy);
  vec4 own = texelFetch(pts_tx, p, 0);
  if (own.w < 0.5) {
    out_cache_a = out_cache_b = out_res_a = out_res_b = out_misc = vec4(0.0);
    return;
  }
  vec3 n = texelFetch(nrm_tx, p, 0).xyz;
  ivec2 lo = textureSize(rec_pos_tx, 0);
  ivec2 g = p / factor;
  vec2 f = vec2(p) + offset;
  float dist = distance(own.xyz, camera.xyz);
  float inv_sigma = 1.0 / max(plane_sigma * dist, 1e-12);
  float own_plane = dot(n, own.xyz);
  vec3 view = (own.xyz - camera.xyz) / max(dist, 1e-30);
  float dist2 = dist * dist;

  vec4 acc_ca = vec4(0.0), acc_cb = vec4(0.0), acc_ra = vec4(0.0), acc_rb = vec4(0.0);
  vec3 acc_lum = vec3(0.0); /* luminance, luminance^2, AO^2 */
  float total = 0.0, spatial = 0.0, best = 0.0;
  bool turned = false;
  float wts[9];
  ivec2 taps[9];
  int t = 0;
  for (int dj = -1; dj <= 1; dj++) {
    for (int di = -1; di <= 1; di++, t++) {
      ivec2 q = g + ivec2(di, dj);
      bool inside = q.x >= 0 && q.y >= 0 && q.x < lo.x && q.y < lo.y;
      if (!inside) {
        q = ivec2(0, 0);
      }
      taps[t] = q;
      vec4 qp = texelFetch(rec_pos_tx, q, 0);
      vec4 qn = texelFetch(rec_nrm_tx, q, 0);
      vec4 qxy = texelFetch(rec_xy_tx, q, 0);
      vec2 d = qxy.xy - f;
      float ws = exp(-dot(d, d) * inv2s2);
      float plane = (dot(n, qp.xyz) - own_plane) * inv_sigma;
      float c = max(dot(n, qn.xyz), 0.0);
      float wr = exp(-plane * plane) * power_of(c, normal_power);
      wr *= (inside ? 1.0 : 0.0) * qp.w;
      if (stretch > 0.0) {
        wr *= stretch_weight(qp.xyz, own.xyz, camera.xyz, view, dist2, stretch);
      }
      best = max(best, wr);
      turned = turned || (wr > 0.0 && c < FLAT_COS);
      float wt = ws * wr;
      wts[t] = wt;
      acc_ca += wt * texelFetch(cache_a_tx, q, 0);
      acc_cb += wt * texelFetch(cache_b_tx, q, 0);
      acc_ra += wt * texelFetch(res_a_tx, q, 0);
      acc_rb += wt * texelFetch(res_b_tx, q, 0);
      acc_lum += wt * vec3(qn.w, qxy.z, qxy.w);
      total += wt;
      spatial += inside ? ws : 0.0;
    }
  }
  float inv = total > 0.0 ? 1.0 / max(total, 1e-30) : 0.0;
  vec4 cache_a = acc_ca * inv, cache_b = acc_cb * inv;
  vec4 res_a = acc_ra * inv, res_b = acc_rb * inv;
  vec3 lum = acc_lum * inv;
  float ao_mean = res_b.z;
  vec2 spread = max(vec2(lum.y - lum.x * lum.x, lum.z - ao_mean * ao_mean), vec2(0.0));
  if (turned) {
    /* The taps' SH at the pixel's own normal, each tap's share of the weights. */
    vec4 own_a = vec4(0.0), own_b = vec4(0.0);
    for (int k = 0; k < sh_count; k++) {
      float y = sh_irradiance_weight(k, n);
      for (int i = 0; i < 9; i++) {
        float share = wts[i] * inv * y;
        ivec2 at = ivec2(2 * taps[i].x, taps[i].y * sh_count + k);
        own_a += share * texelFetch(sh_tx, at, 0);
        own_b += share * texelFetch(sh_tx, at + ivec2(1, 0), 0);
      }
    }
    own_b.z /= M_PI;
    cache_a = own_a;
    cache_b = own_b;
  }
  float cover = total / max(spatial, 1e-30);
  out_cache_a = cache_a;
  out_cache_b = vec4(cache_b.xyz, best);
  out_res_a = res_a;
  out_res_b = vec4(res_b.xyz, cover);
  out_misc = vec4(spread, turned ? 1.0 : 0.0, 1.0);
}

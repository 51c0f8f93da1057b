/* One a-trous pass of `pixel_gather.filter_residual` (see atrous.py): 5 x 5 taps `step` pixels
 * apart, weighted by the B3 spline, the tap's validity, max(0, n_p . n_q)^normal_power (normal_power
 * < 0: the pixel's own exponent, its normal's w) and
 * exp(-(plane distance / (plane_sigma x view distance))^2) (x the stretch term where stretch > 0:
 * `pixel_gather._stretch_into`); with variance guides (guides = 2 or
 * 3) also by exp(-(g_q - g_p)^2 / (noise_k2 (var_p + var_q) + 1e-12)) per guide (SVGF), the
 * variances filtered along with the image.
 *
 * img_a / img_b : channels 0-3 / 4-7 of the image; var : the guides' variances (luminance of all
 * light, [indirect light,] AO); pos : position xyz, w = 1 on valid pixels; nrm : unit normal. */

const float B3[5] = float[5](1.0 / 16.0, 4.0 / 16.0, 6.0 / 16.0, 4.0 / 16.0, 1.0 / 16.0);
const vec3 LUMA = vec3(0.2126, 0.7152, 0.0722);

/* The guides of a pixel's image: luminance of direct + indirect, [indirect,] AO. */
vec3 guides_of(vec4 a, vec4 b)
{
  vec3 direct = a.rgb;
  vec3 indirect = vec3(a.a, b.r, b.g);
  return vec3(dot(direct + indirect, LUMA), dot(indirect, LUMA), b.b);
}

void main()
{
  ivec2 p = ivec2(gl_FragCoord.xy);
  ivec2 size = textureSize(pos_tx, 0);
  vec4 own_pos = texelFetch(pos_tx, p, 0);
  if (own_pos.w < 0.5) {
    out_a = vec4(0.0);
    out_b = vec4(0.0);
    out_var = vec4(0.0);
    return;
  }
  vec4 own_nrm = texelFetch(nrm_tx, p, 0);
  vec3 own_n = own_nrm.xyz;
  float own_power = (normal_power < 0.0) ? own_nrm.w : normal_power;
  float own_plane = dot(own_pos.xyz, own_n);
  float own_dist = distance(own_pos.xyz, camera.xyz);
  float inv_sigma = 1.0 / max(plane_sigma * own_dist, 1e-12);
  /* The stretch term's: the pixel's unit view direction and squared view distance. */
  vec3 own_view = (own_pos.xyz - camera.xyz) / max(own_dist, 1e-30);
  float own_dist2 = own_dist * own_dist;
  vec4 own_a = texelFetch(img_a_tx, p, 0);
  vec4 own_b = texelFetch(img_b_tx, p, 0);
  vec3 own_g = guides_of(own_a, own_b);
  vec4 own_v = texelFetch(var_tx, p, 0);

  vec4 acc_a = vec4(0.0), acc_b = vec4(0.0), acc_v = vec4(0.0);
  vec2 wsum = vec2(0.0); /* the colour channels', AO's */
  for (int dy = 0; dy < 5; dy++) {
    for (int dx = 0; dx < 5; dx++) {
      ivec2 q = p + ivec2(dx - 2, dy - 2) * step;
      if (q.x < 0 || q.y < 0 || q.x >= size.x || q.y >= size.y) {
        continue;
      }
      vec4 qp = texelFetch(pos_tx, q, 0);
      if (qp.w < 0.5) {
        continue;
      }
      vec3 qn = texelFetch(nrm_tx, q, 0).xyz;
      float plane = (dot(qp.xyz, own_n) - own_plane) * inv_sigma;
      float wt = power_of(max(dot(qn, own_n), 0.0), own_power) * (B3[dy] * B3[dx]);
      if (stretch > 0.0 && (dx != 2 || dy != 2)) {
        wt *= stretch_weight(qp.xyz, own_pos.xyz, camera.xyz, own_view, own_dist2, stretch);
      }
      vec4 qa = texelFetch(img_a_tx, q, 0);
      vec4 qb = texelFetch(img_b_tx, q, 0);
      if (guides == 0) {
        wt *= exp(-plane * plane);
        acc_a += wt * qa;
        acc_b += wt * qb;
        wsum += vec2(wt);
        continue;
      }
      vec4 qv = texelFetch(var_tx, q, 0);
      vec3 qg = guides_of(qa, qb);
      vec3 d = qg - own_g;
      vec2 w2;
      if (guides == 3) {
        vec3 e = -(d * d) / (noise_k2 * (own_v.xyz + qv.xyz) + 1e-12);
        /* A colour tap must agree in both luminance guides: the stricter of the two. */
        w2 = vec2(min(e.x, e.y), e.z);
      }
      else {
        /* Two guides: luminance of all light, AO (var.xy). */
        vec2 dg = vec2(d.x, d.z);
        w2 = -(dg * dg) / (noise_k2 * (own_v.xy + qv.xy) + 1e-12);
      }
      w2 = exp(w2 - plane * plane) * wt;
      acc_a += w2.x * qa;
      acc_b += vec4(w2.x * qb.rg, w2.y * qb.b, 0.0);
      vec2 sq = w2 * w2;
      acc_v += (guides == 3) ? vec4(sq.x * qv.xy, sq.y * qv.z, 0.0) : vec4(sq * qv.xy, 0.0, 0.0);
      wsum += w2;
    }
  }
  vec2 total = max(wsum, vec2(1e-12));
  out_a = acc_a / total.x;
  if (guides == 0) {
    out_b = acc_b / total.x;
    out_var = vec4(0.0);
  }
  else {
    out_b = vec4(acc_b.rg / total.x, acc_b.b / total.y, 0.0);
    out_var = (guides == 3) ? vec4(acc_v.xy / (total.x * total.x), acc_v.z / (total.y * total.y), 0.0) :
                              vec4(acc_v.xy / (total * total), 0.0, 0.0);
  }
}

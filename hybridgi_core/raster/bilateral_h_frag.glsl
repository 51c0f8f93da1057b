/* Horizontal cross-bilateral taps: low res (w_lo x h_lo) -> W_full x h_lo. See bilateral_lib. */
void main()
{
  ivec2 o = ivec2(gl_FragCoord.xy);
  ivec2 full = textureSize(full_position_tx, 0);
  int lo_width = textureSize(lo_position_tx, 0).x;
  ivec2 pf = ivec2(o.x, guide_row(o.y, full.y));
  vec4 P = texelFetch(full_position_tx, pf, 0);
  if (P.w < 0.5) {
    out_indirect = vec4(0.0);
    out_direct = vec4(0.0);
    out_ssao = vec4(0.0);
    return;
  }
  vec3 np = texelFetch(full_normal_tx, pf, 0).xyz;
  float zp = texelFetch(full_depth_tx, pf, 0).r;
  float xl = (float(o.x) + 0.5) / float(factor);
  int i0 = int(floor(xl));
  vec4 a0 = vec4(0.0), a1 = vec4(0.0), a2 = vec4(0.0);
  float wsum = 0.0, wspatial = 0.0;
  for (int di = -radius; di <= radius; di++) {
    int i = i0 + di;
    if (i < 0 || i >= lo_width) {
      continue;
    }
    float ws = spatial_weight((float(i) + 0.5) - xl);
    ivec2 q = ivec2(i, o.y);
    float w = ws * bilateral_range_weight(P.xyz, np, zp, texelFetch(lo_position_tx, q, 0),
                                          texelFetch(lo_normal_tx, q, 0).xyz);
    a0 += w * texelFetch(gi_indirect_tx, q, 0);
    a1 += w * texelFetch(gi_direct_tx, q, 0);
    a2 += w * texelFetch(ssao_tx, q, 0);
    wsum += w;
    wspatial += ws;
  }
  /* Range weights can underflow to denormals: 1 / wsum would overflow the half-float targets to
   * inf (NaN downstream). Below a millionth of the spatial weight the taps are "no match" (the
   * confidence in alpha is then ~0 and the vertical taps ignore this row). */
  float inv = (wsum > 1e-6 * wspatial && wsum > 0.0) ? 1.0 / wsum : 0.0;
  out_indirect = a0 * inv;
  /* The direct-from-cache alpha carries the confidence the vertical taps weight by. */
  out_direct = vec4(a1.rgb * inv, (wspatial > 0.0) ? wsum / wspatial : 0.0);
  out_ssao = a2 * inv;
}

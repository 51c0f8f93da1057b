/* Needs bilateral_lib.glsl before it. */

/* Vertical taps at full-res pixel px with guide (P, np, zp). Needs samplers full_position_tx,
 * full_normal_tx (G-buffer) and h_indirect_tx, h_direct_tx, h_ssao_tx (horizontal pass). */
void bilateral_vertical(ivec2 px, vec3 P, vec3 np, float zp,
                        out vec4 indirect, out vec4 direct, out vec4 ssao)
{
  int h_rows = textureSize(h_indirect_tx, 0).y;
  int full_height = textureSize(full_position_tx, 0).y;
  float yl = (float(px.y) + 0.5) / float(factor);
  int j0 = int(floor(yl));
  vec4 a0 = vec4(0.0), a1 = vec4(0.0), a2 = vec4(0.0);
  vec4 b0 = vec4(0.0), b1 = vec4(0.0), b2 = vec4(0.0);
  float wsum = 0.0, wfall = 0.0;
  for (int dj = -radius; dj <= radius; dj++) {
    int j = j0 + dj;
    if (j < 0 || j >= h_rows) {
      continue;
    }
    float ws = spatial_weight((float(j) + 0.5) - yl);
    ivec2 h = ivec2(px.x, j);
    vec4 v0 = texelFetch(h_indirect_tx, h, 0);
    vec4 v1 = texelFetch(h_direct_tx, h, 0);
    vec4 v2 = texelFetch(h_ssao_tx, h, 0);
    float conf = v1.a;
    ivec2 g = ivec2(px.x, guide_row(j, full_height));
    float wr = bilateral_range_weight(P, np, zp, texelFetch(full_position_tx, g, 0),
                                      texelFetch(full_normal_tx, g, 0).xyz);
    float w = ws * wr * conf;
    a0 += w * v0;
    a1 += w * v1;
    a2 += w * v2;
    wsum += w;
    float wf = ws * conf;
    b0 += wf * v0;
    b1 += wf * v1;
    b2 += wf * v2;
    wfall += wf;
  }
  if (wsum > 1e-3 * wfall && wsum > 0.0) {
    indirect = a0 / wsum;
    direct = a1 / wsum;
    ssao = a2 / wsum;
  }
  else if (wfall > 0.0) {
    indirect = b0 / wfall;
    direct = b1 / wfall;
    ssao = b2 / wfall;
  }
  else {
    /* Nothing to interpolate from: no GI, fully open. */
    indirect = vec4(0.0, 0.0, 0.0, 1.0);
    direct = vec4(0.0);
    ssao = vec4(0.0, 0.0, 0.0, 1.0);
  }
}

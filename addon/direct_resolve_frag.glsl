/* Direct light traced by the worker for a (maybe older) camera at a lower resolution, resolved at
 * this frame's pixels: each pixel projects through the source camera and averages the 4x4 source
 * pixels around it, weighted by screen distance, normal agreement and distance to the pixel's
 * plane (joint-bilateral). Pixels the source never saw (disocclusions) fall back to the normal-
 * weighted taps (a = 0.5), then to no lamp light (a = 0): never garbage, never NaN. With `nearest`
 * (flags.x), the best-weighted tap is taken as is (colour codes such as the Cache Cells view must
 * not mix). */
void main()
{
  ivec2 px = ivec2(gl_FragCoord.xy);
  vec4 P = texelFetch(position_tx, px, 0);
  out_direct = vec4(0.0);
  if (P.w < 0.5) {
    return;
  }
  vec3 N = normalize(texelFetch(normal_tx, px, 0).xyz);
  vec4 clip = src_view_proj * vec4(P.xyz, 1.0);
  if (clip.w <= 1e-6) {
    return;
  }
  vec2 sp = (clip.xy / clip.w * 0.5 + 0.5) * vec2(src_size.xy) - 0.5;
  ivec2 base = ivec2(floor(sp));
  float depth = max(view_depth(src_view_z, P.xyz), 0.0);
  float footprint = max(src_footprint.x * depth + src_footprint.y, 1e-6);
  vec3 acc = vec3(0.0);
  float wsum = 0.0;
  vec3 loose = vec3(0.0);
  float wloose = 0.0;
  vec3 best = vec3(0.0);
  float wbest = 0.0;
  /* A source at this frame's resolution (a still view's full-res passes) is interpolated
   * bilinearly: its own pixel's light at the pixel centre, as final renders shade it, not a blur
   * of 1 px across every lamp's shadow edge; a jittered subframe takes its 2x2 taps as the pixel
   * filter's sample would. Lower-resolution sources (a moving view's coarse pass) keep the
   * Gaussian taps. */
  bool sharp = all(equal(src_size.xy, textureSize(position_tx, 0)));
  /* A jittered subframe at a pixel whose light or surface changes within it takes the light the
   * worker traced at what that subframe's ray meets (the edge light: `edge_index_tx` holds the
   * pixel's row in the lists or -1; `edge_light_tx`, `edge_point_tx`, `edge_normal_tx` each
   * row's subframes) when this raster saw the same: the point lies on the traced point's tangent
   * plane and near it, as final renders' `subpixel.same_surface` decides (its SAME_PLANE and
   * SAME_REACH x view depth, defined from it), and the normals agree within 2.6 degrees: the ray
   * met the very point the raster drew, whose interpolated normal is the same, unless a normal
   * map bent the raster's (the worker's light is at the unbent normal; the resolve of the full-res light,
   * traced at the bent normals, serves there). */
  if (flags.y >= 0 && sharp) {
    float row = texelFetch(edge_index_tx, px, 0).r;
    if (row >= 0.0) {
      int at = int(row + 0.5) * flags.z + flags.y;
      ivec2 t = ivec2(at % EDGE_LIST_WIDTH, at / EDGE_LIST_WIDTH);
      vec4 E = texelFetch(edge_light_tx, t, 0);
      vec3 Pe = texelFetch(edge_point_tx, t, 0).xyz;
      vec3 Ne = texelFetch(edge_normal_tx, t, 0).xyz;
      float d = max(view_depth(src_view_z, P.xyz), 1e-6);
      vec3 delta = P.xyz - Pe;
      if (E.a > 0.5 && dot(N, Ne) > 0.999 && abs(dot(Ne, delta)) < SAME_PLANE * d && length(delta) < SAME_REACH * d) {
        out_direct = vec4(E.rgb, 1.0);
        return;
      }
    }
  }
  vec3 tent = vec3(0.0);
  float wtent = 0.0;
  for (int j = -1; j <= 2; j++) {
    for (int i = -1; i <= 2; i++) {
      ivec2 q = base + ivec2(i, j);
      if (any(lessThan(q, ivec2(0))) || any(greaterThanEqual(q, src_size.xy))) {
        continue;
      }
      vec4 Q = texelFetch(src_position_tx, q, 0);
      vec4 D = texelFetch(src_direct_tx, q, 0);
      if (Q.w < 0.5 || D.a < 0.5) {
        continue;
      }
      vec3 M = texelFetch(src_normal_tx, q, 0).xyz;
      vec2 d = vec2(q) - sp;
      float ws = exp(-0.5 * dot(d, d));
      float wn = pow(max(dot(N, M), 0.0), 8.0);
      vec3 delta = Q.xyz - P.xyz;
      float plane = dot(N, delta) / footprint;
      float lateral = length(delta) / (2.0 * footprint);
      float wg = exp(-4.0 * plane * plane - lateral * lateral);
      acc += ws * wn * wg * D.rgb;
      wsum += ws * wn * wg;
      float wt = max(1.0 - abs(d.x), 0.0) * max(1.0 - abs(d.y), 0.0) * wn * wg;
      tent += wt * D.rgb;
      wtent += wt;
      if (ws * wn * wg > wbest) {
        wbest = ws * wn * wg;
        best = D.rgb;
      }
      loose += ws * wn * D.rgb;
      wloose += ws * wn;
    }
  }
  if (flags.x != 0 && wbest > 1e-6) {
    out_direct = vec4(best, 1.0);
  }
  else if (sharp && wtent > 0.05) {
    out_direct = vec4(tent / wtent, 1.0);
  }
  else if (wsum > 1e-3) {
    out_direct = vec4(acc / wsum, 1.0);
  }
  else if (wloose > 1e-4) {
    out_direct = vec4(loose / wloose, 0.5);
  }
}

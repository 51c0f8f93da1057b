/* Stand-alone vertical taps (debug / tests): the same bilateral_vertical the deferred pass runs. */
void main()
{
  ivec2 px = ivec2(gl_FragCoord.xy);
  vec4 P = texelFetch(full_position_tx, px, 0);
  if (P.w < 0.5) {
    out_indirect = vec4(0.0);
    out_direct = vec4(0.0);
    out_ssao = vec4(0.0);
    return;
  }
  vec3 np = texelFetch(full_normal_tx, px, 0).xyz;
  float zp = texelFetch(full_depth_tx, px, 0).r;
  bilateral_vertical(px, P.xyz, np, zp, out_indirect, out_direct, out_ssao);
}

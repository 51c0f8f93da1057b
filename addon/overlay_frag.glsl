/* Multiply factor of the GI overlay (blend MULTIPLY: the view's colour times this). */
void main()
{
  vec2 uv = gl_FragCoord.xy / screen_size.xy;
  ivec2 px = ivec2(uv * vec2(textureSize(position_tx, 0)));
  out_factor = vec4(1.0);
  if (texelFetch(position_tx, px, 0).w < 0.5) {
    return;
  }
  vec3 e_ind = texelFetch(indirect_tx, px, 0).rgb;
  vec3 e_dir = texelFetch(direct_tx, px, 0).rgb;
  float ao = texture(ssao_tx, uv).a;
  const vec3 lum = vec3(0.2126, 0.7152, 0.0722);
  float li = dot(e_ind, lum);
  float ld = dot(e_dir, lum);
  vec3 bleed = (li > 1e-6) ? e_ind / li : vec3(1.0);
  float share = li / max(li + ld, 1e-6);
  vec3 factor = mix(vec3(1.0), bleed, clamp(strength.x * share, 0.0, 1.0));
  factor *= mix(1.0, clamp(ao, 0.0, 1.0), strength.y);
  out_factor = vec4(pow(max(factor, vec3(0.0)), vec3(1.0 / 2.2)), 1.0);
}

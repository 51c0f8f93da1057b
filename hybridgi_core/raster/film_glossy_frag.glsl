/* The film's glossy passes (film_resolve.py), as subpixel.FilmAccumulator.set_glossy makes them
 * from the centre raster's glossy light: filtered by the pixel filter's taps (edge pixels
 * repeated), Glossy Color F(colour), Glossy Direct F(radiance) / F(colour) and Glossy Indirect
 * F(indirect x colour) / F(colour) where the pixel's own colour is (else 0). */

float tap(int i)
{
  return i < 4 ? taps0[i] : taps1[i - 4];
}

vec3 filtered(sampler2D tx, ivec2 px, ivec2 top, bool times_colour)
{
  vec3 total = vec3(0.0);
  for (int dx = -radius; dx <= radius; dx++) {
    vec3 column = vec3(0.0);
    for (int dy = -radius; dy <= radius; dy++) {
      ivec2 q = clamp(px + ivec2(dx, dy), ivec2(0), top);
      vec3 v = texelFetch(tx, q, 0).rgb;
      if (times_colour) {
        v *= texelFetch(colour_tx, q, 0).rgb;
      }
      column += tap(dy + radius) * v;
    }
    total += tap(dx + radius) * column;
  }
  return total;
}

void main()
{
  ivec2 px = ivec2(gl_FragCoord.xy);
  ivec2 top = textureSize(colour_tx, 0) - 1;
  vec3 colour = filtered(colour_tx, px, top, false);
  vec3 radiance = filtered(radiance_tx, px, top, false);
  vec3 bounced = filtered(indirect_tx, px, top, true);
  vec3 raw = texelFetch(colour_tx, px, 0).rgb;
  bool seen = any(greaterThan(raw, vec3(1e-8)));
  bvec3 own = bvec3(seen && colour.x > 1e-8, seen && colour.y > 1e-8, seen && colour.z > 1e-8);
  out_glossy_color = vec4(colour, 1.0);
  out_glossy_direct = vec4(own.x ? radiance.x / colour.x : 0.0, own.y ? radiance.y / colour.y : 0.0,
                           own.z ? radiance.z / colour.z : 0.0, 1.0);
  out_glossy_indirect = vec4(own.x ? bounced.x / colour.x : 0.0, own.y ? bounced.y / colour.y : 0.0,
                             own.z ? bounced.z / colour.z : 0.0, 1.0);
}

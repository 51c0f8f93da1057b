/* The film's resolve (film_resolve.py): the accumulated subframe sums (accumulate_frag.glsl)
 * filtered by the pixel filter's separable taps and turned into Cycles' passes, as the numpy
 * reference subpixel.FilmAccumulator reads them:
 *   F(s) = sum over |dx|, |dy| <= radius of tap(dx) tap(dy) s(px + (dx, dy)), edge pixels repeated;
 *   Combined, its premultiplied twin, Diffuse Color, normal and AO: F(sum) / count;
 *   Diffuse Direct / Indirect: F(light) / F(colour) per channel, a channel without colour taking
 *   the mean ratio of the others (Cycles' safe_divide_even_color), alpha F(light).a / count, and
 *   0 where the pixel's own samples saw no colour (a filtered neighbour's alone is not its own). */

float tap(int i)
{
  return i < 4 ? taps0[i] : taps1[i - 4];
}

vec4 filtered(sampler2D tx, ivec2 px, ivec2 top)
{
  /* Rows first, then columns, as subpixel.filter_image sums them. */
  vec4 total = vec4(0.0);
  for (int dx = -radius; dx <= radius; dx++) {
    vec4 column = vec4(0.0);
    for (int dy = -radius; dy <= radius; dy++) {
      ivec2 q = clamp(px + ivec2(dx, dy), ivec2(0), top);
      column += tap(dy + radius) * texelFetch(tx, q, 0);
    }
    total += tap(dx + radius) * column;
  }
  return total;
}

vec4 divide_even(vec4 light, vec3 color)
{
  bvec3 ok = greaterThan(color, vec3(0.0));
  vec3 ratio = vec3(ok.x ? light.x / color.x : 0.0, ok.y ? light.y / color.y : 0.0,
                    ok.z ? light.z / color.z : 0.0);
  float valid = float(ok.x) + float(ok.y) + float(ok.z);
  float mean = valid > 0.0 ? (ratio.x + ratio.y + ratio.z) / valid : 0.0;
  return vec4(ok.x ? ratio.x : mean, ok.y ? ratio.y : mean, ok.z ? ratio.z : mean, light.w * inv_count);
}

void main()
{
  ivec2 px = ivec2(gl_FragCoord.xy);
  ivec2 top = textureSize(combined_tx, 0) - 1;
  vec4 color = filtered(diffuse_color_tx, px, top);
  out_combined = filtered(combined_tx, px, top) * inv_count;
  out_combined_premultiplied = filtered(combined_premultiplied_tx, px, top) * inv_count;
  out_diffuse_color = color * inv_count;
  out_normal_ao = filtered(normal_ao_tx, px, top) * inv_count;
  vec4 direct = divide_even(filtered(diffuse_direct_tx, px, top), color.rgb);
  vec4 indirect = divide_even(filtered(diffuse_indirect_tx, px, top), color.rgb);
  if (radius > 0) {
    vec3 own = texelFetch(diffuse_color_tx, px, 0).rgb;
    float seen = any(greaterThan(own, vec3(0.0))) ? 1.0 : 0.0;
    direct.rgb *= seen;
    indirect.rgb *= seen;
  }
  out_diffuse_direct = direct;
  out_diffuse_indirect = indirect;
}

/* The image handed to Blender's display: Combined (times `scale`: Cycles' Film Exposure over the
 * subframes a running anti-aliasing sum holds) filtered over its neighbours by Cycles' pixel filter
 * (`taps`, separable: centre, 1, 2 and 3 pixels away, `radius` of them used; what final renders'
 * film does, `subpixel.reconstruction_taps`), with an opaque alpha unless the film is
 * transparent; in the Cache Cells view, the worker's cell colours on geometry (dark grey until
 * they arrive), unfiltered. */
void main()
{
  ivec2 px = ivec2(gl_FragCoord.xy);
  vec4 c;
  if (mode == 1 && texelFetch(position_tx, px, 0).w > 0.5) {
    vec4 cells = texelFetch(cells_tx, px, 0);
    c = vec4((cells.a > 0.0) ? cells.rgb : vec3(0.05), texelFetch(combined_tx, px, 0).a * scale);
  }
  else {
    ivec2 top = textureSize(combined_tx, 0) - 1;
    c = vec4(0.0);
    for (int dy = -radius; dy <= radius; dy++) {
      float wy = taps[abs(dy)];
      for (int dx = -radius; dx <= radius; dx++) {
        c += (wy * taps[abs(dx)]) * texelFetch(combined_tx, clamp(px + ivec2(dx, dy), ivec2(0), top), 0);
      }
    }
    c *= scale;
  }
  out_color = vec4(c.rgb, (opaque != 0) ? 1.0 : c.a);
}

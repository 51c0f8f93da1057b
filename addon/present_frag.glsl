/* The image handed to Blender's display: Combined (times `scale`: Cycles' Film Exposure over the
 * subframes a running anti-aliasing sum holds) with an opaque alpha unless the film is transparent; in the Cache Cells view, the worker's cell colours on geometry (dark grey until
 * they arrive). */
void main()
{
  ivec2 px = ivec2(gl_FragCoord.xy);
  vec4 c = texelFetch(combined_tx, px, 0) * scale;
  if (mode == 1 && texelFetch(position_tx, px, 0).w > 0.5) {
    vec4 cells = texelFetch(cells_tx, px, 0);
    c.rgb = (cells.a > 0.0) ? cells.rgb : vec3(0.05);
  }
  out_color = vec4(c.rgb, (opaque != 0) ? 1.0 : c.a);
}

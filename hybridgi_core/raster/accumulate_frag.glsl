/* Adds one subframe's passes to the running sums of the pixel filter (subpixel.py): the sums of
 * the previous subframes are read from prev_*_tx (ignored on the first) and written back added,
 * into the other set of targets (ping-pong: a target cannot be read while it is drawn into).
 *
 * What is summed follows Cycles' film: Combined as is and premultiplied by its alpha (a
 * transparent film), Diffuse Direct / Indirect times Diffuse Color (divided by the summed colour
 * at the end), Diffuse Color, and the G-buffer normal where the subframe saw geometry (xyz) with AO (w). */

void main()
{
  ivec2 px = ivec2(gl_FragCoord.xy);
  vec4 combined = texelFetch(combined_tx, px, 0);
  vec4 color = texelFetch(diffuse_color_tx, px, 0);
  vec4 direct = texelFetch(diffuse_direct_tx, px, 0);
  vec4 indirect = texelFetch(diffuse_indirect_tx, px, 0);
  float ao = texelFetch(ao_tx, px, 0).r;
  bool hit = texelFetch(position_tx, px, 0).w > 0.5;
  vec3 normal = hit ? texelFetch(normal_tx, px, 0).xyz : vec3(0.0);
  float keep = first != 0 ? 0.0 : 1.0;
  out_combined = keep * texelFetch(prev_combined_tx, px, 0) + combined;
  out_combined_premultiplied = keep * texelFetch(prev_combined_premultiplied_tx, px, 0) +
                               vec4(combined.rgb * combined.a, combined.a);
  out_diffuse_direct = keep * texelFetch(prev_diffuse_direct_tx, px, 0) +
                       vec4(direct.rgb * color.rgb, direct.a);
  out_diffuse_indirect = keep * texelFetch(prev_diffuse_indirect_tx, px, 0) +
                         vec4(indirect.rgb * color.rgb, indirect.a);
  out_diffuse_color = keep * texelFetch(prev_diffuse_color_tx, px, 0) + color;
  out_normal_ao = keep * texelFetch(prev_normal_ao_tx, px, 0) + vec4(normal, ao);
}

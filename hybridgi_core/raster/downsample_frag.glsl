/* Depth-aware downsampling: each low-res pixel copies ONE full-res sample of its
 * factor x factor block (the nearest to the camera), never an average, so positions and normals
 * at depth edges stay on a real surface. Background only where the whole block is background. */
void main()
{
  ivec2 lo = ivec2(gl_FragCoord.xy);
  ivec2 full = textureSize(depth_tx, 0);
  ivec2 origin = lo * factor;
  ivec2 best_px = min(origin, full - 1);
  float best = BACKGROUND_DEPTH * 2.0;
  for (int y = 0; y < factor; y++) {
    for (int x = 0; x < factor; x++) {
      ivec2 p = origin + ivec2(x, y);
      if (p.x >= full.x || p.y >= full.y) {
        continue;
      }
      float d = texelFetch(depth_tx, p, 0).r;
      bool geometry = texelFetch(position_tx, p, 0).w > 0.5;
      if (geometry && d < best) {
        best = d;
        best_px = p;
      }
    }
  }
  out_albedo = texelFetch(albedo_tx, best_px, 0);
  out_normal = texelFetch(normal_tx, best_px, 0);
  out_position = texelFetch(position_tx, best_px, 0);
  out_depth = texelFetch(depth_tx, best_px, 0).r;
  out_material = texelFetch(material_tx, best_px, 0);
}

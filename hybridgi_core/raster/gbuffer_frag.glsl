/* G-buffer MRT. One draw per material: the material's constants are push constants and its
 * texture (or a 1x1 dummy) is `albedo_tx`; `has_texture` bit 1: its rgb is the colour, bit 2:
 * its alpha cuts the surface out below one half (gbuffer.py TEXTURE_COLOR / TEXTURE_ALPHA).
 * `weight_tx` row `material_row` holds the diffuse weight under the material's specular layer
 * against cos(normal, view) (specular.py: Cycles' closure_layering_weight). */

/* The diffuse weight at cosine mu, linear between the table's samples at i / (n - 1). */
float diffuse_weight(float mu)
{
  int n = textureSize(weight_tx, 0).x;
  float x = clamp(mu, 0.0, 1.0) * float(n - 1);
  int i0 = min(int(x), n - 2);
  float a = texelFetch(weight_tx, ivec2(i0, material_row), 0).r;
  float b = texelFetch(weight_tx, ivec2(i0 + 1, material_row), 0).r;
  return mix(a, b, x - float(i0));
}

ivec2 wrap_texel(ivec2 i, ivec2 n)
{
  /* GLSL leaves integer % of negative operands undefined; float mod() floors. */
  return ivec2(mod(vec2(i), vec2(n)));
}

/* Bilinear filtering with REPEAT done by hand, texel centres at (i + 0.5) / size as in Cycles'
 * Linear interpolation: independent of the sampler state the Python API can set. */
vec4 sample_repeat_bilinear4(vec2 uv)
{
  ivec2 size = textureSize(albedo_tx, 0);
  vec2 st = uv * vec2(size) - 0.5;
  vec2 f = floor(st);
  vec2 t = st - f;
  ivec2 i0 = ivec2(f);
  vec4 c00 = texelFetch(albedo_tx, wrap_texel(i0, size), 0);
  vec4 c10 = texelFetch(albedo_tx, wrap_texel(i0 + ivec2(1, 0), size), 0);
  vec4 c01 = texelFetch(albedo_tx, wrap_texel(i0 + ivec2(0, 1), size), 0);
  vec4 c11 = texelFetch(albedo_tx, wrap_texel(i0 + ivec2(1, 1), size), 0);
  return mix(mix(c00, c10, t.x), mix(c01, c11, t.x), t.y);
}

vec3 sample_repeat_bilinear(vec2 uv)
{
  return sample_repeat_bilinear4(uv).rgb;
}

/* Texels seen through one pixel, as Cycles' pixel filter sees them: up to MAX_TAPS x MAX_TAPS
 * bilinear taps spread over the pixel's footprint in UV (the screen derivatives of the UV,
 * widened to `texture_filter` pixels: Cycles' default 1.5-pixel filter for a single raster, the
 * share of one jittered subframe when several integrate the filter), weighted by a Gaussian of
 * about its shape. A texture minified k times gets k x k taps (capped), so a fine texture reads as
 * its average instead of aliasing; a magnified one stays one bilinear tap. */
#define MAX_TAPS 8
vec3 sample_footprint(vec2 uv, vec2 du, vec2 dv)
{
  vec2 size = vec2(textureSize(albedo_tx, 0));
  float texels = max(length(du * size), length(dv * size)) * texture_filter;
  int taps = int(clamp(ceil(texels), 1.0, float(MAX_TAPS)));
  if (taps == 1) {
    return sample_repeat_bilinear(uv);
  }
  vec3 sum = vec3(0.0);
  float weight_sum = 0.0;
  for (int i = 0; i < taps; i++) {
    for (int j = 0; j < taps; j++) {
      vec2 o = ((vec2(i, j) + 0.5) / float(taps) - 0.5) * texture_filter;
      float w = exp(-2.0 * dot(o, o));
      sum += w * sample_repeat_bilinear(uv + o.x * du + o.y * dv);
      weight_sum += w;
    }
  }
  return sum / weight_sum;
}

void main()
{
  /* Derivatives before any branch: they are undefined in non-uniform control flow. */
  vec2 du = dFdx(tex_uv);
  vec2 dv = dFdy(tex_uv);
  vec3 n = normalize(world_nor);
  /* Cycles flips the shading normal of back faces so it faces the camera. */
  if (!gl_FrontFacing) {
    n = -n;
  }
  vec3 albedo = fallback_albedo.rgb;
  /* uv_ok interpolates to < 1 on triangles with any NaN-UV corner: no usable UV there. */
  if ((has_texture & 2) != 0 && uv_ok > 0.999 && sample_repeat_bilinear4(tex_uv).a < 0.5) {
    discard; /* a cut-out hole: what is behind shows (the rays see through it too, cutout.py) */
  }
  if ((has_texture & 1) != 0 && uv_ok > 0.999) {
    albedo = base_color.rgb * sample_footprint(tex_uv, du, dv);
  }
  /* Towards the camera: from the point to the eye, or the orthographic camera's back axis. */
  vec3 to_eye = (eye.w > 0.5) ? normalize(eye.xyz - world_pos) : eye.xyz;
  albedo *= diffuse_weight(dot(n, to_eye));
  out_albedo = vec4(albedo, 1.0);
  out_normal = vec4(n, 1.0);
  out_position = vec4(world_pos, 1.0);
  out_emission = vec4(emission.rgb, 1.0);
  out_depth = view_depth(camera.view_z, world_pos);
  out_material = float(material_row + 1);
}

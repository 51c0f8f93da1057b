/* G-buffer MRT. One draw per material: the material's constants are push constants and its
 * texture (or a 1x1 dummy) is `albedo_tx`; `has_texture` bit 1: its rgb is the colour, bit 2:
 * its alpha cuts the surface out below one half (gbuffer.py TEXTURE_COLOR / TEXTURE_ALPHA).
 * `weight_tx` row `material_row` holds, against cos(normal, view), the factor on the diffuse
 * colour under the material's specular layer and sheen (specular.py, sheen.py: Cycles'
 * closure_layering_weight) in red and the colour its sheen adds in gba. Bit 4: `normal_tx` is
 * a tangent-space normal map, applied in the frame of `world_tan` (xyz tangent, w bitangent sign)
 * as Cycles' Normal Map node applies it (svm_node_normal_map), `normal_strength` its Strength.
 * Bit 8: `bump_tx` (red) is a Bump node's height, applied after the map as Cycles' svm_node_set_bump
 * with `bump_strength` and `bump_distance` (negative: inverted); bit 256 with it: the height lies on a
 * bake's atlas, differenced at most a texel apart (a wider footprint would cross into the next triangle's
 * cell). Bit 16: `emission_tx` is the emitted
 * radiance per texel (an emissive texture), averaged over the pixel's footprint like the colour;
 * without it (or without UVs) the constant `emission`. Bit 32: `emission_tx`'s alpha is the
 * Metallic per texel, added as half of it to `out_material`'s r. Bit 64: a holdout, drawn as a
 * hole (the background's zeros at a depth beyond it). Bit 512: a shadow catcher, position w 2. Bit 128: `rough_tx` (red) is the Roughness
 * per texel, coded with the metallic into the material index's fraction. `out_material`'s gba is
 * the smooth normal before a map or bump bends it (what the CPU takes for the surface: edges, filter guides, ray
 * origins, the bump shadowing term). */

/* Row `row` of the weight table at cosine mu, linear between its samples at i / (n - 1). */
vec4 weight_row(int row, float mu)
{
  int n = textureSize(weight_tx, 0).x;
  float x = clamp(mu, 0.0, 1.0) * float(n - 1);
  int i0 = min(int(x), n - 2);
  vec4 a = texelFetch(weight_tx, ivec2(i0, row), 0);
  vec4 b = texelFetch(weight_tx, ivec2(i0 + 1, row), 0);
  return mix(a, b, x - float(i0));
}

/* The diffuse factor (r) and added sheen colour (gba) at cosine mu: the material's row, or with a
 * Roughness texture (rough_t: the texel's place in rough_range, < 0 without one) its
 * ROUGH_WEIGHT_ROWS rows from `tint_tx`'s fourth texel on, linear between them
 * (gbuffer.weight_table). */
vec4 diffuse_weight(float mu, float rough_t)
{
  float first = texelFetch(tint_tx, ivec2(3, material_row), 0).r;
  if (rough_t < 0.0 || first < 0.0) {
    return weight_row(material_row, mu);
  }
  float y = rough_t * float(ROUGH_WEIGHT_ROWS - 1);
  int r0 = min(int(y), ROUGH_WEIGHT_ROWS - 2);
  int row = int(first + 0.5) + r0;
  return mix(weight_row(row, mu), weight_row(row + 1, mu), y - float(r0));
}

ivec2 wrap_texel(ivec2 i, ivec2 n)
{
  /* GLSL leaves integer % of negative operands undefined; float mod() floors. */
  return ivec2(mod(vec2(i), vec2(n)));
}

/* Bilinear filtering with REPEAT done by hand, texel centres at (i + 0.5) / size as in Cycles'
 * Linear interpolation: independent of the sampler state the Python API can set. */
vec4 sample_repeat_bilinear4(sampler2D tx, vec2 uv)
{
  ivec2 size = textureSize(tx, 0);
  vec2 st = uv * vec2(size) - 0.5;
  vec2 f = floor(st);
  vec2 t = st - f;
  ivec2 i0 = ivec2(f);
  vec4 c00 = texelFetch(tx, wrap_texel(i0, size), 0);
  vec4 c10 = texelFetch(tx, wrap_texel(i0 + ivec2(1, 0), size), 0);
  vec4 c01 = texelFetch(tx, wrap_texel(i0 + ivec2(0, 1), size), 0);
  vec4 c11 = texelFetch(tx, wrap_texel(i0 + ivec2(1, 1), size), 0);
  return mix(mix(c00, c10, t.x), mix(c01, c11, t.x), t.y);
}

vec3 sample_repeat_bilinear(sampler2D tx, vec2 uv)
{
  return sample_repeat_bilinear4(tx, uv).rgb;
}

/* Texels seen through one pixel, as Cycles' pixel filter sees them: up to MAX_TAPS x MAX_TAPS
 * bilinear taps spread over the pixel's footprint in UV (the screen derivatives of the UV,
 * widened to `texture_filter` pixels: Cycles' default 1.5-pixel filter for a single raster, the
 * share of one jittered subframe when several integrate the filter), weighted by a Gaussian of
 * about its shape. A texture minified k times gets k x k taps (capped), so a fine texture reads as
 * its average instead of aliasing; a magnified one stays one bilinear tap. */
#define MAX_TAPS 8
vec4 sample_footprint4(sampler2D tx, vec2 uv, vec2 du, vec2 dv)
{
  vec2 size = vec2(textureSize(tx, 0));
  float texels = max(length(du * size), length(dv * size)) * texture_filter;
  int taps = int(clamp(ceil(texels), 1.0, float(MAX_TAPS)));
  if (taps == 1) {
    return sample_repeat_bilinear4(tx, uv);
  }
  vec4 sum = vec4(0.0);
  float weight_sum = 0.0;
  for (int i = 0; i < taps; i++) {
    for (int j = 0; j < taps; j++) {
      vec2 o = ((vec2(i, j) + 0.5) / float(taps) - 0.5) * texture_filter;
      float w = exp(-2.0 * dot(o, o));
      sum += w * sample_repeat_bilinear4(tx, uv + o.x * du + o.y * dv);
      weight_sum += w;
    }
  }
  return sum / weight_sum;
}

vec3 sample_footprint(sampler2D tx, vec2 uv, vec2 du, vec2 dv)
{
  return sample_footprint4(tx, uv, du, dv).rgb;
}

/* Cycles' ensure_valid_specular_reflection (kernel/geom/shader_data.h): the shading normal N
 * turned towards the geometric normal Ng just enough that the mirror direction of the view
 * direction I (both facing the same side as Ng) stays above the surface. */
vec3 ensure_valid_specular_reflection(vec3 Ng, vec3 I, vec3 N)
{
  vec3 R = 2.0 * dot(N, I) * N - I;
  float Iz = dot(I, Ng);
  float threshold = min(0.9 * Iz, 0.01);
  if (dot(Ng, R) >= threshold) {
    return N;
  }
  vec3 X = N - dot(N, Ng) * Ng;
  float len = length(X);
  X = (len > 1e-12) ? X / len : N;
  float Ix = dot(I, X);
  float a = Ix * Ix + Iz * Iz;
  float b = 2.0 * (a + Iz * threshold);
  float c = (threshold + Iz) * (threshold + Iz);
  float root = sqrt(max(b * b - 16.0 * a * c, 0.0));
  float Nz2 = (Ix < 0.0) ? 0.25 * (b + root) / a : 0.25 * (b - root) / a;
  float Nx = sqrt(max(1.0 - Nz2, 0.0));
  float Nz = sqrt(max(Nz2, 0.0));
  return Nx * X + Nz * Ng;
}

/* The shading normal N made valid against the facet (Cycles' Ng: the facet's normal on the
 * camera's side) for the view direction I. */
vec3 valid_reflection(vec3 facet, vec3 I, vec3 N)
{
  float facet_len = length(facet);
  if (facet_len <= 0.0) {
    return N;
  }
  vec3 ng = facet / facet_len;
  if (dot(ng, I) < 0.0) {
    ng = -ng;
  }
  return ensure_valid_specular_reflection(ng, I, N);
}

/* Cycles' svm_node_set_bump over the height in `bump_tx`: the surface gradient of the height from
 * its UV gradient (central differences over half a texel or the pixel's footprint, whichever is
 * wider) and the screen derivatives of UV and position (Cycles' ray differentials), then
 * normalize(|det| N - distance sign(det) surfgrad), mixed with N by the strength. */
vec3 bumped_normal(vec3 n_in, vec3 dpdx, vec3 dpdy, vec2 du, vec2 dv)
{
  vec2 size = vec2(textureSize(bump_tx, 0));
  vec2 h_step = max(0.5 / size, 0.5 * max(abs(du), abs(dv)));
  if ((has_texture & 256) != 0) {
    h_step = min(h_step, 1.0 / size);
  }
  float hu = (sample_repeat_bilinear4(bump_tx, map_uv + vec2(h_step.x, 0.0)).r -
              sample_repeat_bilinear4(bump_tx, map_uv - vec2(h_step.x, 0.0)).r) / (2.0 * h_step.x);
  float hv = (sample_repeat_bilinear4(bump_tx, map_uv + vec2(0.0, h_step.y)).r -
              sample_repeat_bilinear4(bump_tx, map_uv - vec2(0.0, h_step.y)).r) / (2.0 * h_step.y);
  float dhdx = hu * du.x + hv * du.y;
  float dhdy = hu * dv.x + hv * dv.y;
  vec3 rx = cross(dpdy, n_in);
  vec3 ry = cross(n_in, dpdx);
  float det = dot(dpdx, rx);
  vec3 surfgrad = dhdx * rx + dhdy * ry;
  vec3 bent = abs(det) * n_in - bump_distance * sign(det) * surfgrad;
  float len = length(bent);
  if (len <= 0.0) {
    return n_in;
  }
  vec3 mixed = bump_strength * (bent / len) + (1.0 - bump_strength) * n_in;
  float mixed_len = length(mixed);
  return (mixed_len > 0.0) ? mixed / mixed_len : n_in;
}

void main()
{
  /* Derivatives before any branch: they are undefined in non-uniform control flow. */
  vec2 du = dFdx(tex_uv);
  vec2 dv = dFdy(tex_uv);
  /* The normal and bump maps' UVs: the mesh's own where a baked colour moved tex_uv onto the
   * bake's atlas, else tex_uv. */
  vec2 map_du = dFdx(map_uv);
  vec2 map_dv = dFdy(map_uv);
  vec3 dpdx = dFdx(world_pos);
  vec3 dpdy = dFdy(world_pos);
  vec3 facet = cross(dpdx, dpdy);
  vec3 n = normalize(world_nor);
  /* Cycles flips the shading normal of back faces so it faces the camera. */
  if (!gl_FrontFacing) {
    n = -n;
  }
  /* The smooth surface before any map bends it: the material target's gba. */
  vec3 n_surface = n;
  vec3 albedo = fallback_albedo.rgb;
  /* uv_ok interpolates to < 1 on triangles with any NaN-UV corner: no usable UV there. */
  if ((has_texture & 2) != 0 && uv_ok > 0.999 && sample_repeat_bilinear4(albedo_tx, tex_uv).a < 0.5) {
    discard; /* a cut-out hole: what is behind shows (the rays see through it too, cutout.py) */
  }
  if (base_color.a < 1.0) {
    /* A surface seen with a chance (Material.coverage, in base_color.a): each pixel's threshold
     * (interleaved gradient noise, Jimenez 2014) moves by the golden ratio per subframe
     * (`dither`), so a pixel's subframes see it in about that share of their samples. */
    float threshold = fract(52.9829189 * fract(dot(gl_FragCoord.xy, vec2(0.06711056, 0.00583715))));
    if (fract(threshold + dither) >= base_color.a) {
      discard;
    }
  }
  /* A textured metal (`tint_tx` row: mean texel, two main axes of its texture's colours, alpha
   * 1: glossy.metal_tint_basis): the texel's coordinates along the axes go to the albedo and
   * emission targets' alphas, its metallic lobe's colour per pixel. */
  vec2 tint = vec2(0.0);
  if ((has_texture & 1) != 0 && uv_ok > 0.999) {
    vec3 texel = sample_footprint(albedo_tx, tex_uv, du, dv);
    albedo = base_color.rgb * texel;
    vec4 tint_mean = texelFetch(tint_tx, ivec2(0, material_row), 0);
    if (tint_mean.a > 0.5) {
      /* Alpha 2: under a Metallic texture the drawn colour is the diffuse base; the metal's own
       * colour is `metal_tx`'s, premultiplied by the Metallic in its alpha (`metal_texels`): the
       * footprint's metal texels alone, or the mean (no tint) where there are none. */
      vec3 source = texel;
      if (tint_mean.a > 1.5) {
        vec4 metal = sample_footprint4(metal_tx, tex_uv, du, dv);
        source = (metal.a > 1e-4) ? metal.rgb / metal.a : tint_mean.rgb;
      }
      vec3 d = source - tint_mean.rgb;
      tint = vec2(dot(d, texelFetch(tint_tx, ivec2(1, material_row), 0).rgb),
                  dot(d, texelFetch(tint_tx, ivec2(2, material_row), 0).rgb));
    }
  }
  /* Towards the camera: from the point to the eye, or the orthographic camera's back axis. */
  vec3 to_eye = (eye.w > 0.5) ? normalize(eye.xyz - world_pos) : eye.xyz;
  if ((has_texture & 4) != 0 && uv_ok > 0.999 && dot(world_tan.xyz, world_tan.xyz) > 1e-12) {
    /* Cycles' svm_node_normal_map, tangent space: the unnormalized interpolated normal and
     * tangent, B = sign cross(N, T), the map's texels averaged over the pixel's footprint. */
    vec3 c = 2.0 * sample_footprint(normal_tx, map_uv, map_du, map_dv) - 1.0;
    vec3 bitangent = world_tan.w * cross(world_nor, world_tan.xyz);
    vec3 mapped = c.x * world_tan.xyz + c.y * bitangent + c.z * world_nor;
    float len = length(mapped);
    mapped = (len > 1e-12) ? mapped / len : normalize(world_nor);
    if (!gl_FrontFacing) {
      mapped = -mapped;
    }
    if (normal_strength != 1.0) {
      vec3 mixed = n + (mapped - n) * max(normal_strength, 0.0);
      float mixed_len = length(mixed);
      mapped = (mixed_len > 1e-12) ? mixed / mixed_len : n;
    }
    n = valid_reflection(facet, to_eye, mapped);
  }
  if ((has_texture & 8) != 0 && uv_ok > 0.999) {
    n = valid_reflection(facet, to_eye, bumped_normal(n, dpdx, dpdy, map_du, map_dv));
  }
  /* A Roughness texture's texel, as its place in rough_range (the glossy variant below and the
   * diffuse weight); without UVs the middle. */
  float rough_t = -1.0;
  if ((has_texture & 128) != 0) {
    rough_t = 0.5;
    if (uv_ok > 0.999) {
      float r = sample_footprint(rough_tx, tex_uv, du, dv).x;
      rough_t = clamp((r - rough_range.x) / max(rough_range.y - rough_range.x, 1e-6), 0.0, 1.0);
    }
  }
  vec4 weight = diffuse_weight(dot(n, to_eye), rough_t);
  albedo = albedo * weight.r + weight.gba;
  out_albedo = vec4(albedo, tint.x);
  out_normal = vec4(n, 1.0);
  out_position = vec4(world_pos, 1.0);
  vec3 emitted = emission.rgb;
  float row = float(material_row + 1);
  float metal = -1.0; /* the Metallic texel, where one is read */
  if ((has_texture & 48) != 0 && uv_ok > 0.999) {
    vec4 glow = sample_footprint4(emission_tx, tex_uv, du, dv);
    if ((has_texture & 16) != 0) {
      emitted = glow.rgb;
    }
    if ((has_texture & 32) != 0) {
      /* The Metallic texel as the index's fraction: the CPU's glossy lobes pick by it. */
      metal = clamp(glow.a, 0.0, 1.0);
      row += 0.5 * metal;
    }
  }
  if ((has_texture & 128) != 0) {
    /* A Roughness texture: the fraction codes the glossy variant, (metallic step x roughness
     * steps + roughness step + 0.5) / variants, rough_range = (lo, hi, metallic steps, roughness
     * steps) (glossy_image.material_rows decodes it). Without UVs, the middle step. */
    float t = rough_t;
    float steps = rough_range.w;
    float ri = floor(t * (steps - 1.0) + 0.5);
    float mi = (metal >= 0.0) ? floor(metal * (rough_range.z - 1.0) + 0.5) : 0.0;
    row = float(material_row + 1) + (mi * steps + ri + 0.5) / (rough_range.z * steps);
  }
  out_emission = vec4(emitted, tint.y);
  out_depth = view_depth(camera.view_z, world_pos);
  out_material = vec4(row, n_surface);
  if ((has_texture & 512) != 0) {
    out_position.w = 2.0; /* a shadow catcher (gbuffer.py TEXTURE_CATCHER, catcher.py) */
  }
  if ((has_texture & 64) != 0) {
    /* A holdout: a hole the background shows through, marked by its depth (gbuffer.py HOLDOUT_DEPTH). */
    out_albedo = vec4(0.0);
    out_normal = vec4(0.0);
    out_position = vec4(0.0);
    out_emission = vec4(0.0);
    out_depth = 1.5 * BACKGROUND_DEPTH;
    out_material = vec4(0.0);
  }
}

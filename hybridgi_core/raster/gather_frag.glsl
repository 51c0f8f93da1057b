/* Step 6 on the GPU: gather the 3D irradiance cache at the low-res G-buffer points.
 * A line-by-line port of hybridgi_core/evaluate.py (`corner_weights` + `gather`): same biased
 * point, same 8 cells and trilinear weights, same back-face term, the same visibility (exact
 * corner mask, or Chebyshev on the nearest octahedral depth texel), same minimum weights and
 * normalization, same SH irradiance. Keep the two in step: tests compare them.
 *
 * Cache data, texel-fetched (no filtering, so nothing differs from numpy):
 *  cache_tx (RGBA32F 2D), 2K texels per cell at linear index flat * 2K + s, laid row-major
 *    over the texture width: s < K: (sh_direct[k].rgb, ao_sh[k]); s >= K: (sh_indirect[k].rgb,
 *    s == K ? valid : 0)
 *  depth_tx (RG32F 2D), D*D texels per cell at flat * D*D + texel: (mean, mean square) distance
 *  mask_tx (R32F, low res): bit c set = corner c visible (evaluate.corner_visibility)
 *  surface_tx (low res, read with bent_lobes = 1): gba = the smooth surface normal under a normal
 *    map; the light is then read through the bent lobe (bump.irradiance_kernel), AO keeps the cosine
 *  lobe_tx (RGBA32F, LOBE_ANGLES x 2): bump.lobe_moments, texel (i, 0) = (m0, mx, mz, mxx),
 *    (i, 1) = (myy, mzz, mxz, 0) */

#define MODE_PLAIN 0
#define MODE_CHEBYSHEV 1
#define MODE_MASK 2

#define MIN_CHEBYSHEV 0.05
#define MIN_WEIGHT 1e-4
#define BACKFACE_FLOOR 0.2

vec4 fetch_linear(sampler2D tx, int index)
{
  int width = textureSize(tx, 0).x;
  return texelFetch(tx, ivec2(index % width, index / width), 0);
}

int flatten_cell(ivec3 ijk)
{
  return ijk.x + grid_dims.x * (ijk.y + grid_dims.y * ijk.z);
}

vec3 cell_center(ivec3 ijk)
{
  return grid_lo_cell.xyz + (vec3(ijk) + 0.5) * grid_lo_cell.w;
}

/* sampling.octahedral_texel */
int octahedral_texel(vec3 d, int size)
{
  float s = abs(d.x) + abs(d.y) + abs(d.z);
  vec2 p = d.xy / max(s, 1e-20);
  if (d.z < 0.0) {
    vec2 sgn = vec2(p.x >= 0.0 ? 1.0 : -1.0, p.y >= 0.0 ? 1.0 : -1.0);
    p = (1.0 - abs(p.yx)) * sgn;
  }
  vec2 uv = p * 0.5 + 0.5;
  ivec2 t = ivec2(clamp(floor(uv * float(size)), 0.0, float(size - 1)));
  return t.y * size + t.x;
}

/* bump.irradiance_kernel: the SH weights of the irradiance a diffuse closure with bent normal n
 * over the smooth surface normal g receives (no light from below the surface, Cycles' bump
 * shadowing term above it). Returns false where n is not bent (the plain cosine weights hold). */
bool bent_kernel(vec3 g, vec3 n, out float k[9])
{
  const float C0 = 0.28209479177387814;
  const float C1 = 0.4886025119029199;
  const float C2 = 1.0925484305920792;
  const float C3 = 0.31539156525252005;
  const float C4 = 0.5462742152960396;
  float c = clamp(dot(g, n), -1.0, 1.0);
  if (c >= 1.0 - 1e-6) {
    return false;
  }
  vec3 t = n - c * g;
  t /= max(length(t), 1e-30);
  vec3 b = cross(g, t);
  int angles = textureSize(lobe_tx, 0).x;
  float x = acos(clamp(c, 0.0, 1.0)) / (0.5 * M_PI) * float(angles - 1);
  int i0 = min(int(x), angles - 2);
  float f = x - float(i0);
  vec4 a = mix(texelFetch(lobe_tx, ivec2(i0, 0), 0), texelFetch(lobe_tx, ivec2(i0 + 1, 0), 0), f);
  vec4 e = mix(texelFetch(lobe_tx, ivec2(i0, 1), 0), texelFetch(lobe_tx, ivec2(i0 + 1, 1), 0), f);
  float m0 = a.x, mx = a.y, mz = a.z, mxx = a.w, myy = e.x, mzz = e.y, mxz = e.z;
  vec3 first = mx * t + mz * g;
  /* second moments int (w.e_i)(w.e_j) K in world axes, as a symmetric matrix */
  mat3 s2 = mxx * outerProduct(t, t) + myy * outerProduct(b, b) + mzz * outerProduct(g, g) +
            mxz * (outerProduct(t, g) + outerProduct(g, t));
  k[0] = C0 * m0;
  k[1] = C1 * first.y;
  k[2] = C1 * first.z;
  k[3] = C1 * first.x;
  k[4] = C2 * s2[0][1];
  k[5] = C2 * s2[1][2];
  k[6] = C3 * (3.0 * s2[2][2] - m0);
  k[7] = C2 * s2[0][2];
  k[8] = C4 * (s2[0][0] - s2[1][1]);
  return true;
}

void main()
{
  ivec2 px = ivec2(gl_FragCoord.xy);
  vec4 P = texelFetch(position_tx, px, 0);
  if (P.w < 0.5) {
    out_indirect = vec4(0.0, 0.0, 0.0, 1.0);
    out_direct = vec4(0.0);
    return;
  }
  /* evaluate.py takes normals as given (already unit up to half-float rounding). */
  vec3 n = texelFetch(normal_tx, px, 0).xyz;
  float cell = grid_lo_cell.w;
  int K = grid_dims.w;
  int slots = 2 * K;
  vec3 p = P.xyz + n * (normal_bias * cell);

  /* grid.corner_cells */
  vec3 g = (p - grid_lo_cell.xyz) / cell - 0.5;
  vec3 base = floor(g);
  vec3 f = g - base;
  ivec3 ibase = ivec3(base);

  int flats[8];
  float w[8];
  float tri[8];
  float cosv[8];
  float masked_sum = 0.0;
  int mask_bits = int(texelFetch(mask_tx, px, 0).r + 0.5);
  for (int c = 0; c < 8; c++) {
    ivec3 o = ivec3(c & 1, (c >> 1) & 1, (c >> 2) & 1);
    ivec3 ijk = clamp(ibase + o, ivec3(0), grid_dims.xyz - 1);
    flats[c] = flatten_cell(ijk);
    vec3 wa = mix(1.0 - f, f, vec3(o));
    tri[c] = wa.x * wa.y * wa.z;
    float valid = fetch_linear(cache_tx, flats[c] * slots + K).a;
    w[c] = tri[c] * valid;
    cosv[c] = 1.0;
    if (mode != MODE_PLAIN) {
      vec3 to_cell = cell_center(ijk) - p;
      float dist = length(to_cell);
      vec3 dir = (dist > 1e-6) ? to_cell / max(dist, 1e-6) : n;
      float cs = dot(dir, n);
      cosv[c] = cs;
      float h = (cs + 1.0) * 0.5;
      w[c] *= h * h + BACKFACE_FLOOR;
      if (mode == MODE_CHEBYSHEV) {
        int texel = octahedral_texel(-dir, depth_texels);
        vec2 m = fetch_linear(depth_tx, flats[c] * depth_texels * depth_texels + texel).rg;
        float var = max(m.y - m.x * m.x, 1e-4 * cell * cell);
        float excess = max(dist - m.x, 0.0);
        float cheb = var / (var + excess * excess);
        cheb = (dist <= m.x) ? 1.0 : cheb * cheb * cheb;
        w[c] *= max(cheb, MIN_CHEBYSHEV);
      }
    }
  }
  if (mode != MODE_PLAIN) {
    /* evaluate._mask_or_keep: drop masked-out neighbours unless none would be left. */
    float keep_sum = 0.0;
    for (int c = 0; c < 8; c++) {
      bool keep = (mode == MODE_MASK) ? ((mask_bits >> c) & 1) != 0 : cosv[c] > 0.0;
      keep_sum += keep ? w[c] : 0.0;
    }
    if (keep_sum > 0.0) {
      for (int c = 0; c < 8; c++) {
        bool keep = (mode == MODE_MASK) ? ((mask_bits >> c) & 1) != 0 : cosv[c] > 0.0;
        w[c] = keep ? w[c] : 0.0;
      }
    }
    for (int c = 0; c < 8; c++) {
      w[c] = (w[c] > 0.0) ? max(w[c], MIN_WEIGHT * tri[c]) : 0.0;
    }
  }
  float total = 0.0;
  for (int c = 0; c < 8; c++) {
    total += w[c];
  }

  /* The light's SH weights: the cosine lobe at n, or the bent lobe over the smooth surface. */
  float lobe[9];
  bool bent = false;
  if (bent_lobes != 0) {
    vec3 smooth_n = texelFetch(surface_tx, px, 0).yzw;
    bent = dot(smooth_n, smooth_n) > 0.25 && bent_kernel(smooth_n, n, lobe);
  }
  if (!bent) {
    for (int k = 0; k < 9; k++) {
      lobe[k] = sh_irradiance_weight(k, n);
    }
  }
  vec3 direct = vec3(0.0);
  vec3 indirect = vec3(0.0);
  float ao_irr = 0.0;
  if (total > 0.0) {
    for (int c = 0; c < 8; c++) {
      float wc = w[c] / total;
      if (wc == 0.0) {
        continue;
      }
      int first = flats[c] * slots;
      for (int k = 0; k < K; k++) {
        float yk = wc * lobe[k];
        vec4 dir_ao = fetch_linear(cache_tx, first + k);
        vec4 ind = fetch_linear(cache_tx, first + K + k);
        direct += yk * dir_ao.rgb;
        ao_irr += wc * sh_irradiance_weight(k, n) * dir_ao.a;
        indirect += yk * ind.rgb;
      }
    }
  }
  float ao = (total > 0.0) ? clamp(ao_irr / M_PI, 0.0, 1.0) : 1.0;
  out_indirect = vec4(max(indirect, 0.0), ao);
  out_direct = vec4(max(direct, 0.0), 0.0);
}

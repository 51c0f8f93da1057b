/* Helpers shared by the raster passes (prepended as text: create_from_info has no #include). */

#define M_PI 3.14159265358979323846
/* Must match passes.BACKGROUND_DEPTH. */
#define BACKGROUND_DEPTH 1.0e10

/* View-axis distance (Cycles' Depth pass) of world point p; view_z = third row of the view
 * matrix, so the camera looks along -z and depth is positive in front of it. */
float view_depth(vec4 view_z, vec3 p)
{
  return -(dot(view_z.xyz, p) + view_z.w);
}

/* Orthonormal basis around unit n (Duff et al. 2017, branch-free and continuous but at one pole). */
mat3 basis_from_normal(vec3 n)
{
  float s = (n.z >= 0.0) ? 1.0 : -1.0;
  float a = -1.0 / (s + n.z);
  float b = n.x * n.y * a;
  vec3 t = vec3(1.0 + s * n.x * n.x * a, s * b, -s * n.x);
  vec3 bt = vec3(b, s + n.y * n.y * a, -n.y);
  return mat3(t, bt, n);
}

/* Interleaved gradient noise (Jimenez 2014): cheap per-pixel decorrelation, deterministic. */
float pixel_noise(vec2 px, float salt)
{
  px += salt * vec2(47.0, 17.0);
  return fract(52.9829189 * fract(dot(px, vec2(0.06711056, 0.00583715))));
}

/* sh.basis x sh.cosine_scale, Sloan's order and constants: irradiance weight of coefficient k
 * at normal n. */
float sh_irradiance_weight(int k, vec3 n)
{
  const float C0 = 0.28209479177387814;
  const float C1 = 0.4886025119029199;
  const float C2 = 1.0925484305920792;
  const float C3 = 0.31539156525252005;
  const float C4 = 0.5462742152960396;
  const float A1 = 2.0 * M_PI / 3.0;
  const float A2 = M_PI / 4.0;
  switch (k) {
    case 0: return M_PI * C0;
    case 1: return A1 * C1 * n.y;
    case 2: return A1 * C1 * n.z;
    case 3: return A1 * C1 * n.x;
    case 4: return A2 * C2 * n.x * n.y;
    case 5: return A2 * C2 * n.y * n.z;
    case 6: return A2 * C3 * (3.0 * n.z * n.z - 1.0);
    case 7: return A2 * C2 * n.x * n.z;
    default: return A2 * C4 * (n.x * n.x - n.y * n.y);
  }
}

/* c^exponent for the range weights of the filters: the default exponent 8 by squarings, as
 * numpy's `_power_into` (no pow() per tap). */
float power_of(float c, float exponent)
{
  if (exponent == 8.0) {
    float c2 = c * c;
    float c4 = c2 * c2;
    return c4 * c4;
  }
  return pow(c, exponent);
}

/* pixel_gather._stretch_into: a tap at tap_p seen from a pixel at own_p (unit view direction
 * own_dir from the eye at eye_p, squared view distance own_d2) weighs 1 up to the distance the
 * same screen step spans on a surface facing the camera (view distance x the chord of the two
 * view directions) and exp(-((ratio - 1) / falloff)^2) beyond. (Parameter names that no pass
 * uses for a push constant: Blender defines those as names.) */
float stretch_weight(vec3 tap_p, vec3 own_p, vec3 eye_p, vec3 own_dir, float own_d2, float falloff)
{
  vec3 to_q = tap_p - eye_p;
  vec3 chord_v = to_q / max(length(to_q), 1e-30) - own_dir;
  vec3 apart = tap_p - own_p;
  float ratio = sqrt(dot(apart, apart) / max(dot(chord_v, chord_v) * own_d2, 1e-30));
  float s = max(ratio - 1.0, 0.0) / falloff;
  return exp(-s * s);
}

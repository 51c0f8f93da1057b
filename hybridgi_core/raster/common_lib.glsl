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

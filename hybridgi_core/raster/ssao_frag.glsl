/* Screen-space AO + near-field colour bleeding at low resolution (seed step 7).
 *
 * Screen-space rays: `samples` cosine-weighted directions around the normal, each marched in
 * MARCH_STEPS points up to `radius` metres. A direction is occluded at its first point S whose
 * pixel shows a surface Q in front of S and above P's tangent plane (the plane test removes the
 * false occlusion nearest-texel depth gives on flat or grazing surfaces). Marching rather than
 * one point per sample makes AO the share of rays blocked within `radius`, the same meaning as
 * the ray-traced AO it is blended with (Cycles' AO distance). With cosine sampling,
 * AO = 1 - blocked share, and the irradiance reflected by the occluders is
 *   E_bounce = (1/N) sum_blocked albedo_Q * E_Q
 * since a Lambertian occluder of albedo a lit by E has radiance a E / pi and
 * E = (pi/N) sum L for cosine-distributed directions. Only occluders whose visible side faces P
 * send light to it. */

#define MARCH_STEPS 4

void main()
{
  ivec2 px = ivec2(gl_FragCoord.xy);
  ivec2 size = textureSize(position_tx, 0);
  vec4 P = texelFetch(position_tx, px, 0);
  if (P.w < 0.5) {
    out_ssao = vec4(0.0, 0.0, 0.0, 1.0);
    return;
  }
  /* normal_gba: normal_tx is the material target, whose gba hold the smooth surface normal under
   * a normal map; the hemisphere of geometric occluders is the surface's, not the bent normal's. */
  vec4 nt = texelFetch(normal_tx, px, 0);
  vec3 n = normalize(normal_gba != 0 ? nt.yzw : nt.xyz);
  mat3 frame = basis_from_normal(n);
  float noise_a = pixel_noise(vec2(px), 0.0);
  float noise_b = pixel_noise(vec2(px), 1.0);
  float noise_c = pixel_noise(vec2(px), 2.0);
  vec3 origin = P.xyz + n * (0.01 * radius);

  float occlusion = 0.0;
  vec3 bounce = vec3(0.0);
  for (int k = 0; k < samples; k++) {
    /* Stratified in u1, golden-ratio sequence in u2, rotated per pixel. */
    float u1 = fract((float(k) + 0.5) / float(samples) + noise_a);
    float u2 = fract(float(k) * 0.6180339887 + noise_b);
    float jitter = fract(float(k) * 0.7548776662 + noise_c);
    float r = sqrt(u1);
    float phi = 2.0 * M_PI * u2;
    vec3 dir = frame * vec3(r * cos(phi), r * sin(phi), sqrt(max(0.0, 1.0 - u1)));

    for (int m = 0; m < MARCH_STEPS; m++) {
      vec3 S = origin + dir * (radius * (float(m) + jitter) / float(MARCH_STEPS));
      vec4 clip = camera.view_proj * vec4(S, 1.0);
      if (clip.w <= 0.0) {
        break;
      }
      vec2 ndc = clip.xy / clip.w;
      if (any(greaterThan(abs(ndc), vec2(1.0)))) {
        break; /* left the screen: unknown, counted as open */
      }
      ivec2 q = clamp(ivec2((ndc * 0.5 + 0.5) * vec2(size)), ivec2(0), size - 1);
      vec4 Q = texelFetch(position_tx, q, 0);
      if (Q.w < 0.5) {
        continue;
      }
      float zS = view_depth(camera.view_z, S);
      float zQ = view_depth(camera.view_z, Q.xyz);
      vec3 v = Q.xyz - P.xyz;
      bool hidden = zQ < zS - (1e-3 * zS + 0.002 * radius);
      bool above = dot(v, n) > 0.02 * radius;
      if (!(hidden && above)) {
        continue;
      }
      /* Occluders 1-2 radii away fade out: a far foreground object must not darken P. */
      float range = smoothstep(0.5, 1.0, radius / max(length(v), 1e-6));
      occlusion += range;
      vec3 nq = texelFetch(normal_tx, q, 0).xyz;
      if (dot(nq, -v) > 0.0) {
        vec3 lit = (has_irradiance != 0) ? texelFetch(irradiance_tx, q, 0).rgb : vec3(1.0);
        bounce += range * texelFetch(albedo_tx, q, 0).rgb * lit;
      }
      break;
    }
  }
  float inv_n = 1.0 / float(samples);
  float ao = clamp(1.0 - strength * occlusion * inv_n, 0.0, 1.0);
  out_ssao = vec4(strength * bounce * inv_n, ao);
}

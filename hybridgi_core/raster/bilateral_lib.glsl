/* Separable cross-bilateral upsampling of low-res GI to full resolution (seed step 8).
 *
 * Scheme. Low-res pixel (i, j) holds GI at one real surface point (the downsample's
 * representative of block (i, j)). The guide of intermediate texel (X, j) is the full-res
 * G-buffer sample g(X, j) = (X, guide_row(j)), the centre row of low-res row j.
 *  1. Horizontal pass (bilateral_h_frag.glsl), output W_full x H_low:
 *       H(X, j) = sum_i ws(i - x_lo) wr(g(X, j), lo(i, j)) GI(i, j) / sum_i ws wr
 *     plus confidence c(X, j) = sum_i ws wr / sum_i ws (0 when no tap lies on g's surface).
 *  2. Vertical taps, fused into the deferred pass (bilateral_vertical below), full res:
 *       GI(X, Y) = sum_j ws(j - y_lo) wr(G(X, Y), g(X, j)) c(X, j) H(X, j) / sum_j (...)
 *     The guides g(X, j) are read from the full-res G-buffer itself: no extra guide target.
 * ws: Gaussian in low-res pixels (sigma). wr: exp(-(plane distance / (plane_sigma * depth))^2)
 * x max(0, n_p . n_q)^normal_power; the plane distance of q to p's tangent plane is zero along a
 * surface even at grazing angles, where depth differences are not. Where no vertical tap matches
 * (thin features), the confidence-weighted spatial average is used instead of black.
 * Push constants shared by both passes: factor, radius, sigma, plane_sigma, normal_power. */

int guide_row(int j, int full_height)
{
  return min(j * factor + factor / 2, full_height - 1);
}

float spatial_weight(float d)
{
  return exp(-0.5 * d * d / (sigma * sigma));
}

float bilateral_range_weight(vec3 p, vec3 np, float zp, vec4 q, vec3 nq)
{
  if (q.w < 0.5) {
    return 0.0; /* background holds no GI */
  }
  float plane = dot(np, q.xyz - p) / (plane_sigma * max(zp, 1e-4));
  float wn = (normal_power > 0.0) ? pow(max(dot(np, nq), 0.0), normal_power) : 1.0;
  return exp(-plane * plane) * wn;
}

#version 330 core
// One source for GLSL 3.30 core, 4.10 core and ES 3.00 (OpenGL 3.3/4.1, OpenGL ES 3.0, WebGL 2): the runtime replaces
// the #version line above with each target's header, nothing else (docs/shaders.md).
// Per-Gaussian set-up of the EWA splatter: one point sprite (SPLAT_POINTS 1) or one instanced quad (SPLAT_POINTS 0,
// 4 vertices, triangle strip) per Gaussian; the fragment shader makes every per-pixel decision exactly.
// The maths is the numerics contract (docs/numerics.md). Each function names its torch twin in
// exporter/model/splat_math.py (same name, same arguments; uniforms become trailing arguments there), or says that it
// is not a contract step (runtime/splat/gl.py NON_CONTRACT_GLSL_FUNCTIONS); tests/test_mirror_names.py checks both.
// #defines injected by the runtime after the header (runtime/splat/programs.py shader_defines), never re-typed:
//   contract constants, from gaussiantalker.sdk.numerics (the values the torch reference imports), used here:
//     LOW_PASS_PX2, EXTENT_SIGMAS, ALPHA_MIN, FINITE_LIMIT, DET_MIN_RELATIVE, COV2D_HUGE_PX2
//   the GL renderer's own rasterisation settings, from runtime/splat/programs.py (no torch counterpart), used here:
//     QUAD_SLACK_PX, BOX_SLACK_REL, SPLAT_POINTS (1: point sprites, 0: instanced quads; set per program)

uniform mat3 u_R;           // world -> camera rotation (R * p applies the camera's R)
uniform vec3 u_t;           // world -> camera translation
uniform vec4 u_intrinsics;  // fx, fy, cx, cy in pixels
uniform vec2 u_image_size;  // W, H in pixels
uniform vec4 u_fov_limits;  // x/z min, x/z max, y/z min, y/z max (Camera.fov_clamp_limits)

in vec3 in_mean;     // [N, 3] world position
in vec3 in_cov_a;    // [N, 3] world covariance xx, xy, xz
in vec3 in_cov_b;    // [N, 3] world covariance yy, yz, zz
in vec4 in_rgba;     // [N, 4] colour rgb, opacity

flat out vec2 v_center;   // projected centre, continuous pixel coordinates (+y down)
flat out vec3 v_shape;    // inverse 2D covariance in completed-square form (A, k, q): see alpha_shape
flat out float v_radius;  // extent radius r in pixels
flat out vec4 v_rgba;     // colour, opacity times reliability_fade

// Torch twin: `world_to_camera` (exporter/model/splat_math.py).
// Camera-space position p = R * mean + t of a world position (docs/numerics.md, "Camera and pixel centres").
vec3 world_to_camera(vec3 mean) {
    return u_R * mean + u_t;
}

// Torch twin: `camera_to_pixel` (exporter/model/splat_math.py).
// u = fx * X / Z + cx, v = fy * Y / Z + cy in continuous pixel coordinates: pixel (x, y) has its centre at
// (x + 1/2, y + 1/2) (docs/numerics.md, "Camera and pixel centres").
vec2 camera_to_pixel(vec3 p_cam) {
    return vec2(u_intrinsics.x * p_cam.x / p_cam.z + u_intrinsics.z,
                u_intrinsics.y * p_cam.y / p_cam.z + u_intrinsics.w);
}

// Torch twin: `clamped_ratios` (exporter/model/splat_math.py).
// x/z and y/z clamped to the widened field of view (Camera.fov_clamp_limits), before forming J.
vec2 clamped_ratios(vec3 p_cam) {
    return vec2(clamp(p_cam.x / p_cam.z, u_fov_limits.x, u_fov_limits.y),
                clamp(p_cam.y / p_cam.z, u_fov_limits.z, u_fov_limits.w));
}

// Torch twin: `sigma_matrix` (exporter/model/splat_math.py).
// Packed world covariance (xx, xy, xz), (yy, yz, zz) -> symmetric 3x3.
mat3 sigma_matrix(vec3 cov_a, vec3 cov_b) {
    return mat3(cov_a.x, cov_a.y, cov_a.z,
                cov_a.y, cov_b.x, cov_b.y,
                cov_a.z, cov_b.y, cov_b.z);
}

// Torch twin: `covariance_2d` (exporter/model/splat_math.py).
// J W Sigma W^T J^T with x/z, y/z clamped to the widened field of view before forming J, plus LOW_PASS_PX2 on the
// diagonal (docs/numerics.md, "2D covariance and field-of-view clamp"). Returns (a, b, c) = [[a, b], [b, c]].
vec3 covariance_2d(vec3 p_cam, vec3 cov_a, vec3 cov_b) {
    float z = p_cam.z;
    vec2 ratios = clamped_ratios(p_cam);
    vec3 j0 = vec3(u_intrinsics.x / z, 0.0, -u_intrinsics.x * ratios.x / z);  // row 0 of J
    vec3 j1 = vec3(0.0, u_intrinsics.y / z, -u_intrinsics.y * ratios.y / z);  // row 1 of J
    vec3 m0 = j0 * u_R;  // row 0 of J W
    vec3 m1 = j1 * u_R;  // row 1 of J W
    mat3 sigma = sigma_matrix(cov_a, cov_b);
    vec3 s0 = sigma * m0;
    vec3 s1 = sigma * m1;
    return vec3(dot(m0, s0) + LOW_PASS_PX2, dot(m0, s1), dot(m1, s1) + LOW_PASS_PX2);
}

// Torch twin: `cov2d_scale` (exporter/model/splat_math.py).
// max(|a|, |c|) of a 2D covariance: dividing by it keeps every product of its entries below 1 (no float32
// overflow); it is data, not a constant, so the compiler cannot fold or reassociate it away.
float cov2d_scale(vec3 cov2d) {
    return max(abs(cov2d.x), abs(cov2d.z));
}

// Torch twin: `reliable` (exporter/model/splat_math.py).
// det where it exceeds DET_MIN_RELATIVE * products (rounding_products), else 0: noise is culled.
float reliable(float det, float products) {
    return det > DET_MIN_RELATIVE * products ? det : 0.0;
}

// Torch twin: `rounding_products` (exporter/model/splat_math.py).
// What the rounding noise of x z - y^2 scales with, each entry computed as a sum whose terms' absolute values sum
// to `magnitude`: (|x|bar |z| + |x| |z|bar) / 2 + |y| |y|bar; without cancellation, |x z| + y^2.
float rounding_products(vec3 value, vec3 magnitude) {
    return 0.5 * (magnitude.x * abs(value.z) + abs(value.x) * magnitude.z) + abs(value.y) * magnitude.y;
}

// Torch twin: `determinant_and_noise` (exporter/model/splat_math.py).
// (det, noise): det of covariance_2d (its (a, b, c) passed in) / cov2d_scale^2 in the least-cancelling of two
// forms, and the rounding_products its float32 rounding noise scales with (docs/numerics.md, "2D determinant
// conditioning").
// a c - b^2 cancels badly where J's rows are nearly parallel (grazing view angles). Replacing J's second row by its
// part orthogonal to the first (closed form; a shear of determinant 1) and adding the low-pass filter as
// det(A + l I) = det A + l (tr A + l) avoids that; the form with the smaller second diagonal entry is used.
vec2 determinant_and_noise(vec3 p_cam, vec3 cov_a, vec3 cov_b, vec3 cov2d) {
    float z = p_cam.z;
    vec2 ratios = clamped_ratios(p_cam);
    float g = 1.0 / (1.0 + ratios.x * ratios.x);
    vec3 j0 = vec3(u_intrinsics.x / z, 0.0, -u_intrinsics.x * ratios.x / z);  // row 0 of J
    vec3 j1 = (u_intrinsics.y / z) * vec3(-(ratios.x * g) * ratios.y, 1.0, -ratios.y * g);  // row 1, sheared
    vec3 m0 = j0 * u_R;
    vec3 m1 = j1 * u_R;
    mat3 sigma = sigma_matrix(cov_a, cov_b);
    vec3 s0 = sigma * m0;
    vec3 s1 = sigma * m1;
    vec3 sheared_cov = vec3(dot(m0, s0), dot(m0, s1), dot(m1, s1));  // A in the sheared basis, no low-pass
    bool use_sheared = sheared_cov.z + LOW_PASS_PX2 < cov2d.z;
    float s = cov2d_scale(cov2d);
    vec3 abc = cov2d / s;  // low-pass included
    vec3 n = sheared_cov / s;
    float low_pass = LOW_PASS_PX2 / s;
    float sheared = (n.x * n.z - n.y * n.y) + low_pass * (abc.x + abc.z - low_pass);  // det A + l (tr A + l)
    // Magnitudes of both forms' entries: the quadratic forms over |rows| and |Sigma| (the plain second row as
    // covariance_2d forms it).
    vec3 j1_plain = vec3(0.0, u_intrinsics.y / z, -u_intrinsics.y * ratios.y / z);
    vec3 r0 = abs(m0);
    vec3 r1 = abs(m1);
    vec3 r2 = abs(j1_plain * u_R);
    mat3 sigma_abs = mat3(abs(sigma[0]), abs(sigma[1]), abs(sigma[2]));
    vec3 w0 = sigma_abs * r0;
    vec3 w1 = sigma_abs * r1;
    vec3 w2 = sigma_abs * r2;
    float m0_mag = dot(r0, w0);
    vec3 sheared_mag = vec3(m0_mag, dot(r0, w1), dot(r1, w1)) / s;
    vec3 plain_mag = vec3(m0_mag + LOW_PASS_PX2, dot(r0, w2), dot(r2, w2) + LOW_PASS_PX2) / s;
    return use_sheared ? vec2(sheared, rounding_products(n, sheared_mag))
                       : vec2(abc.x * abc.z - abc.y * abc.y, rounding_products(abc, plain_mag));
}

// Torch twin: `covariance_2d_determinant` (exporter/model/splat_math.py).
// det of covariance_2d (its (a, b, c) passed in) / cov2d_scale^2 from determinant_and_noise, 0 where it is lost in
// rounding noise (reliable): the only 2D determinant of the contract.
float covariance_2d_determinant(vec3 p_cam, vec3 cov_a, vec3 cov_b, vec3 cov2d) {
    vec2 det_noise = determinant_and_noise(p_cam, cov_a, cov_b, cov2d);
    return reliable(det_noise.x, det_noise.y);
}

// Torch twin: `reliability_fade` (exporter/model/splat_math.py).
// The factor in [0, 1] the opacity is multiplied by: 1 - exp(-ALPHA_MIN (rho - 1)), 0 for rho <= 1, with rho = det /
// (DET_MIN_RELATIVE noise) of determinant_and_noise: no alpha reaches ALPHA_MIN just above the cut, so a rounding
// difference in rho there changes no pixel, and further up the frame moves continuously (docs/numerics.md,
// "Reliability fade"). main calls it and covariance_2d_determinant on the same arguments: one
// determinant_and_noise after inlining.
float reliability_fade(vec3 p_cam, vec3 cov_a, vec3 cov_b, vec3 cov2d) {
    vec2 det_noise = determinant_and_noise(p_cam, cov_a, cov_b, cov2d);
    float threshold = DET_MIN_RELATIVE * det_noise.y;
    if (!(det_noise.x > threshold)) {
        return 0.0;
    }
    // threshold == 0 with det > 0 (the noise underflowed) is a fully reliable det, as det / 0 = inf would say.
    return threshold > 0.0 ? 1.0 - exp(-ALPHA_MIN * ((det_noise.x - threshold) / threshold)) : 1.0;
}

// Torch twin: `conic_from_cov2d` (exporter/model/splat_math.py).
// Inverse of the 2D covariance, packed (A, B, C), from covariance_2d_determinant (det / cov2d_scale^2).
vec3 conic_from_cov2d(vec3 cov2d, float det) {
    float s = cov2d_scale(cov2d);
    vec3 abc = cov2d / s;
    float det_over_s = det * s;  // det(cov2d) / s
    return vec3(abc.z / det_over_s, -abc.y / det_over_s, abc.x / det_over_s);
}

// Torch twin: `alpha_shape` (exporter/model/splat_math.py).
// The conic in completed-square form (A, k, q): d^T cov2d^-1 d = A (dx - k dy)^2 + q dy^2, with A = c / det,
// k = b / c, q = 1 / c. A sum of non-negative terms: on the ridge of a long, thin splat, A dx^2 + 2 B dx dy + C dy^2
// cancels and float32 rounding can make it positive (skipping a pixel that should be fully drawn); this cannot.
vec3 alpha_shape(vec3 cov2d, float det) {
    float c = cov2d.z == 0.0 ? 1.0 : cov2d.z;  // c == 0 is not positive definite: culled (det <= 0)
    return vec3(conic_from_cov2d(cov2d, det).x, cov2d.y / c, 1.0 / c);
}

// Torch twin: `radius_of` (exporter/model/splat_math.py).
// EXTENT_SIGMAS * sqrt(lambda_max) of a symmetric 2x2 (a, b, c), negative roots taken as 0.
float radius_of(vec3 cov2d) {
    float mid = 0.5 * (cov2d.x + cov2d.z);
    float lambda_max = mid + sqrt(max(mid * mid - (cov2d.x * cov2d.z - cov2d.y * cov2d.y), 0.0));
    return EXTENT_SIGMAS * sqrt(max(lambda_max, 0.0));
}

// Torch twin: `extent_radius` (exporter/model/splat_math.py).
// r = EXTENT_SIGMAS * sqrt(lambda_max) of the dilated 2D covariance, exact, no rounding. Where 0.5 (a + c) >
// COV2D_HUGE_PX2 it is evaluated on cov2d / cov2d_scale and scaled back, so mid^2 cannot overflow
// (docs/numerics.md, "Extent radius").
float extent_radius(vec3 cov2d) {
    float s = cov2d_scale(cov2d);
    return 0.5 * (cov2d.x + cov2d.z) > COV2D_HUGE_PX2 ? radius_of(cov2d / s) * sqrt(s) : radius_of(cov2d);
}

// Torch twin: `extent_power_bound` (exporter/model/splat_math.py).
// Largest |power| reachable with |dx|, |dy| <= radius (bounded by FINITE_LIMIT in screen_bounded).
float extent_power_bound(vec3 conic, float radius) {
    return (abs(conic.x) + 2.0 * abs(conic.y) + abs(conic.z)) * radius * radius;
}

// Torch twin: `screen_bounded` (exporter/model/splat_math.py).
// Whether every screen-space value stays below FINITE_LIMIT in magnitude, so the per-pixel float32 maths stays
// finite (docs/numerics.md, "Near plane and culling"). Comparisons with NaN are false, so NaN fails (max() and
// min() may drop a NaN, so none is used here).
bool screen_bounded(vec2 center, vec3 conic, vec3 shape, float radius) {
    return all(lessThan(abs(vec4(center, radius, extent_power_bound(conic, radius))), vec4(FINITE_LIMIT)))
           && all(lessThan(abs(conic), vec3(FINITE_LIMIT))) && all(lessThan(abs(shape), vec3(FINITE_LIMIT)));
}

// Not a contract step (rasterisation only): the smallest box of whole pixels that can hold a pixel passing the
// fragment shader's exact tests. Those are |dx| <= r, |dy| <= r (extent) and alpha >= ALPHA_MIN, which needs
// d^T cov2d^-1 d <= q_max = 2 ln(opacity / ALPHA_MIN), an ellipse whose bounding box is |dx| <= sqrt(q_max a),
// |dy| <= sqrt(q_max c). Both bounds are widened (BOX_SLACK_REL, QUAD_SLACK_PX) against float rounding, so no
// passing pixel is ever left out. The box is clipped to the image and its edges are integer pixel coordinates,
// half a pixel from every pixel centre, so the rasteriser's sub-pixel snapping cannot add or drop a pixel.
// Returns (lo.x, lo.y, hi.x, hi.y); empty when hi <= lo on an axis.
vec4 pixel_box(vec2 center, vec3 cov2d, float radius, float opacity) {
    float q_max = 2.0 * log(max(opacity, ALPHA_MIN) / ALPHA_MIN) * (1.0 + BOX_SLACK_REL) + BOX_SLACK_REL;
    vec2 half_size = min(vec2(radius), sqrt(q_max * cov2d.xz)) + (0.5 + QUAD_SLACK_PX);
    vec2 lo = clamp(ceil(center - half_size), vec2(0.0), u_image_size);
    vec2 hi = clamp(floor(center + half_size), vec2(0.0), u_image_size);
    return vec4(lo, hi);
}

// Not a contract step (rasterisation only): in-image 4x4 pixel blocks plus 4x2 half-blocks touched by the pixel
// range [start, start + side) of an axis of length size; a cost to minimise (llvmpipe shades 4x4 blocks, and runs
// the shader on 4x2 halves that have a covered pixel). Pixels outside the image are never shaded.
float block_cost(float start, float side, float size) {
    float a = max(start, 0.0);
    float b = min(start + side, size);
    if (!(b > a)) {
        return 0.0;
    }
    float blocks = floor((b - 1.0) * 0.25) - floor(a * 0.25) + 1.0;
    float halves = floor((b - 1.0) * 0.5) - floor(a * 0.5) + 1.0;
    return 8.0 * blocks + halves;
}

// Not a contract step (rasterisation only): the start of a point sprite of `side` pixels along one axis, for the
// box edges [lo, hi) on that axis (hi - lo <= side) and an image of `size` pixels. Any start in
// [max(hi - side, -side / 2), min(lo, size - side / 2)] holds the box and keeps the point's centre inside the
// image (GL drops a point whose centre is outside the view volume); that range is never empty. Of three
// candidates in it (a multiple of 4 at or below lo, the smallest multiple of 4 that still reaches hi, the old
// centred start) the one touching the fewest blocks (block_cost) is taken, the first on a tie. All of them are
// whole or half pixels, so the square's edges never pass through a pixel centre inside the box.
float point_start(float lo, float hi, float side, float size) {
    float lowest = max(hi - side, -0.5 * side);
    float highest = min(lo, size - 0.5 * side);
    float below = clamp(4.0 * floor(lo * 0.25), lowest, highest);
    float above = clamp(4.0 * ceil((hi - side) * 0.25), lowest, highest);
    float centred = 0.5 * (lo + hi - side);
    float best = below;
    float cost = block_cost(below, side, size);
    float above_cost = block_cost(above, side, size);
    if (above_cost < cost) {
        best = above;
        cost = above_cost;
    }
    if (block_cost(centred, side, size) < cost) {
        best = centred;
    }
    return best;
}

// Not a contract step (rasterisation only): drops this Gaussian's primitive.
void cull() {
    gl_Position = vec4(-2.0, -2.0, 0.0, 1.0);  // outside the view: a point is dropped, a quad has no area
    gl_PointSize = 1.0;
    v_center = vec2(0.0);
    v_shape = vec3(0.0);
    v_radius = -1.0;
    v_rgba = vec4(0.0);
}

void main() {
    vec3 p_cam = world_to_camera(in_mean);
    vec2 center = camera_to_pixel(p_cam);
    vec3 cov2d = covariance_2d(p_cam, in_cov_a, in_cov_b);
    float det = covariance_2d_determinant(p_cam, in_cov_a, in_cov_b, cov2d);
    if (!(det > 0.0)) {  // contract: skip a Gaussian whose 2D determinant is not positive (NaN fails too)
        cull();
        return;
    }
    float radius = extent_radius(cov2d);
    vec3 conic = conic_from_cov2d(cov2d, det);
    vec3 shape = alpha_shape(cov2d, det);
    if (!screen_bounded(center, conic, shape, radius)) {  // contract: anything non-finite is culled
        cull();
        return;
    }
    // contract: the opacity as composited, faded where the determinant is near its noise
    float opacity = in_rgba.a * reliability_fade(p_cam, in_cov_a, in_cov_b, cov2d);
    vec4 box = pixel_box(center, cov2d, radius, opacity);
    if (!(box.z > box.x && box.w > box.y)) {  // off screen, or no pixel can reach ALPHA_MIN
        cull();
        return;
    }
    // Pixel coordinates map to NDC without a y flip: framebuffer row j holds image row j, and read-back
    // returns the top image row first.
#if SPLAT_POINTS
    // One point sprite per Gaussian: a square holding the box, its side the box's longer side; along the shorter
    // side it is placed to touch the fewest pixel blocks (point_start). The host only draws Gaussians whose box
    // surely fits the largest point size this way.
    float side = max(box.z - box.x, box.w - box.y);
    vec2 start = vec2(point_start(box.x, box.z, side, u_image_size.x), point_start(box.y, box.w, side, u_image_size.y));
    gl_PointSize = side;
    gl_Position = vec4((start + 0.5 * side) / u_image_size * 2.0 - 1.0, 0.0, 1.0);
#else
    // One instanced quad (triangle strip) per Gaussian: vertex 0..3 is corner (x: id & 1, y: id >> 1) of the box.
    vec2 corner = vec2(float(gl_VertexID & 1), float(gl_VertexID >> 1));
    gl_Position = vec4(mix(box.xy, box.zw, corner) / u_image_size * 2.0 - 1.0, 0.0, 1.0);
#endif
    v_center = center;
    v_shape = shape;
    v_radius = radius;
    v_rgba = vec4(in_rgba.rgb, opacity);
}

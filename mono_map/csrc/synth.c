/* Compiled float32 kernels of the synthetic renderer (mono_map.data.synth.kernels loads it).

   Each kernel fuses a chain of numpy's elementwise float32 operations into one pass over the rays, in
   numpy's operation order and types, so the results are numpy's bit for bit (tests/test_synth.py). */
#include "synth_materials.h"

#include <math.h>
#include <stdint.h>

#define F(x) ((float) (x))          /* a python float constant as numpy rounds it for a float32 operation */

/* ---- noise.py: hash01, cell_noise, value_noise, fbm ---- */
static inline uint32_t mix(uint32_t h)
{
    h ^= h >> 16; h *= 0x7FEB352Du; h ^= h >> 15; h *= 0x846CA68Bu; return h ^ (h >> 16);
}
static inline uint32_t seed_hash(int64_t seed)
{
    return (uint32_t) ((((uint64_t) seed & 0xFFFFFFFFull) * 0xC2B2AE3Dull + 0x165667B1ull) & 0xFFFFFFFFull);
}
/* numpy's float -> int32 cast on x86 (cvtt: out of range or NaN -> INT32_MIN), viewed as uint32 */
static inline uint32_t f2u(float a)
{
    return (a >= -2147483648.0f && a < 2147483648.0f) ? (uint32_t) (int32_t) a : 0x80000000u;
}
static inline uint32_t d2u(double a)
{
    return (a > -2147483649.0 && a < 2147483648.0) ? (uint32_t) (int32_t) a : 0x80000000u;
}
static inline float u01(uint32_t h) { return (float) (h >> 8) * F(1.0 / 16777216.0); }
static inline float hash2(uint32_t h0, uint32_t a, uint32_t b)
{
    return u01(mix((h0 ^ (a * 0x9E3779B1u)) ^ (b * 0x85EBCA77u)));
}
static inline float hash3(uint32_t h0, uint32_t a, uint32_t b, uint32_t c)
{
    return u01(mix(mix((h0 ^ (a * 0x9E3779B1u)) ^ (b * 0x85EBCA77u)) ^ (c * 0xC2B2AE3Du)));
}
static inline float cell(uint32_t h0, float x, float y, float s)
{
    return hash2(h0, f2u(floorf(x * s)), f2u(floorf(y * s)));
}
static inline float vnoise(uint32_t h0, float x, float y, float s)
{
    float fx = x * s, fy = y * s;
    float ix = floorf(fx), iy = floorf(fy);
    float tx = fx - ix, ty = fy - iy;
    tx = tx * tx * (3.0f - 2.0f * tx);
    ty = ty * ty * (3.0f - 2.0f * ty);
    uint32_t x0 = f2u(ix), x1 = f2u(ix + 1.0f), y0 = f2u(iy), y1 = f2u(iy + 1.0f);
    float a = hash2(h0, x0, y0), b = hash2(h0, x1, y0), c = hash2(h0, x0, y1), d = hash2(h0, x1, y1);
    return (a + (b - a) * tx) * (1.0f - ty) + (c + (d - c) * tx) * ty;
}
/* numpy's float32 remainder (npy_divmodf): fmod, moved to the divisor's sign */
static inline float np_modf(float a, float b)
{
    float mod = fmodf(a, b);
    if (!b) return mod;
    if (mod) { if ((b < 0) != (mod < 0)) mod += b; }
    else mod = copysignf(0.0f, b);
    return mod;
}
/* np.clip(x, 0, 1) */
static inline float clip01(float x)
{
    if (!isnan(x)) x = x > 0.0f ? x : 0.0f;
    if (!isnan(x)) x = x < 1.0f ? x : 1.0f;
    return x;
}

static inline float clipf(float x, float lo, float hi)
{
    if (!isnan(x)) x = x > lo ? x : lo;
    if (!isnan(x)) x = x < hi ? x : hi;
    return x;
}

/* ---- materials.py ---- */
typedef struct {
    const int32_t *tris; const uint8_t *tri_mat; const int32_t *tri_obj; const uint8_t *tri_junc;
    const float *vert_ls; int64_t n_obj; const float *obj_color; const int32_t *obj_flags;
    const double *obj_origin; const float *obj_params; int64_t seed; double glass_fraction;
    double left, right, lane, sidewalk, vehicle_detail;
} town_t;

/* barycentric_attr: the ground attributes (l, s) at a hit */
static inline void ground_ls(const town_t *T, int64_t prim, const float *uv, float *l, float *s)
{
    const int32_t *f = T->tris + 3 * prim;
    const float u = uv[0], v = uv[1], w = 1.0f - u - v;
    const float *A = T->vert_ls;
    *l = w * A[2 * f[0]] + u * A[2 * f[1]] + v * A[2 * f[2]];
    *s = w * A[2 * f[0] + 1] + u * A[2 * f[1] + 1] + v * A[2 * f[2] + 1];
}
static inline int is_road(const town_t *T, float l) { return l > F(T->left) && l < F(T->right); }

/* l of the road hits (ground, between the road edges), in hit order; returns their number */
int64_t syn_road_l(const town_t *T, int64_t n, const int64_t *prim, const float *uvs, float *out)
{
    int64_t k = 0;
    for (int64_t i = 0; i < n; ++i) {
        if (T->tri_mat[prim[i]] != MAT_GROUND) continue;
        float l, s;
        ground_ls(T, prim[i], uvs + 2 * i, &l, &s);
        if (is_road(T, l)) out[k++] = l;
    }
    return k;
}

static inline int64_t obj_index(const town_t *T, int64_t prim)
{
    int64_t o = T->tri_obj[prim];
    return o < 0 ? o + T->n_obj : o;                 /* numpy's negative index */
}
static inline void set3(float *a, float x, float y, float z) { a[0] = x; a[1] = y; a[2] = z; }

/* _face_tangent: (n_z, 0, -n_x) / max(|.|, 1e-6) in float64 */
static inline void face_tangent(const float *n, double *t)
{
    t[0] = (double) n[2]; t[1] = 0.0; t[2] = (double) (-n[0]);
    double nm = sqrt((t[0] * t[0] + t[1] * t[1]) + t[2] * t[2]);
    nm = nm > 1e-6 ? nm : 1e-6;
    t[0] /= nm; t[1] /= nm; t[2] /= nm;
}

static void ground(const town_t *T, int64_t prim, const float *uv, const float *P, int lidar, const float *track,
                   int64_t *k_road, float *a, float *rf, uint8_t *reg)
{
    const int64_t seed = T->seed;
    const double lane = T->lane, sw = T->sidewalk;
    float l, s;
    ground_ls(T, prim, uv, &l, &s);
    const float x = P[0], z = P[2];
    const int road = is_road(T, l);
    const int side = !road && l > F(T->left - sw) && l < F(T->right + sw);
    *rf = F(0.35); *reg = 3;
    if (road) {
        const int centre = fabsf(l + F(lane / 2)) < F(0.075) && np_modf(s, F(9.0)) < F(3.0);
        const int edge = fabsf(l - F(lane / 2)) < F(0.065) || fabsf(l + F(1.5 * lane)) < F(0.065);
        const int mark = (centre || edge) && !T->tri_junc[prim];
        *reg = mark ? 1 : 0;
        const float blot = vnoise(seed_hash(seed + 1), x, z, F(1.0 / 4.0));
        *rf = mark ? F(0.78) : F(0.10) + F(0.08) * blot;
        if (!lidar) {
            const float grain = cell(seed_hash(seed + 2), x, z, F(1.0 / 0.05));
            float g = F(0.21) + F(0.08) * blot + F(0.07) * (grain - F(0.5)) - F(0.025) * track[(*k_road)++];
            if (vnoise(seed_hash(seed + 3), x, z, F(1.0 / 7.0)) > F(0.78)) g = g * F(0.8);
            if (mark) g = F(0.52) + F(0.30) * vnoise(seed_hash(seed + 4), x, z, F(1.0 / 0.5));
            set3(a, g * F(0.96), g * F(0.98), g * F(1.0));
        }
    } else if (side) {
        *rf = F(0.30); *reg = 2;
        if (!lidar) {
            const float fl = floorf(l * 2.0f), fs = floorf(s * 2.0f);
            const int joint = (l - fl * F(0.5)) < F(0.02) || (s - fs * F(0.5)) < F(0.02);
            float g = F(0.46) + F(0.10) * (hash2(seed_hash(seed + 5), f2u(fl), f2u(fs)) - F(0.5))
                      + F(0.05) * (cell(seed_hash(seed + 6), x, z, F(1.0 / 0.04)) - F(0.5));
            g = g * (1.0f - F(0.12) * vnoise(seed_hash(seed + 7), x, z, F(1.0 / 3.0)));
            if (joint) g = g * F(0.7);
            set3(a, g * F(1.0), g * F(0.97), g * F(0.91));
        }
    } else if (!lidar) {
        const float gn = vnoise(seed_hash(seed + 8), x, z, F(1.0 / 2.0));
        const float gg = cell(seed_hash(seed + 9), x, z, F(1.0 / 0.05));
        const float k = F(0.8) + F(0.4) * gg;
        const float G1[3] = {F(0.19), F(0.26), F(0.10)}, G2[3] = {F(0.33), F(0.29), F(0.18)};
        for (int c = 0; c < 3; ++c) a[c] = ((1.0f - gn) * G1[c] + gn * G2[c]) * k;
    }
}

static void facade(const town_t *T, int64_t prim, const float *P, const float *n, int lidar,
                   float *a, float *mir, float *rf, uint8_t *gl)
{
    const int64_t seed = T->seed, oid = obj_index(T, prim);
    const uint32_t uo = (uint32_t) T->tri_obj[prim];
    const int32_t flags = T->obj_flags[oid];
    const double *o = T->obj_origin + 3 * oid;
    const float *prm = T->obj_params + 4 * oid;
    const float su = prm[0], fh = prm[1], ww = prm[2], wh = prm[3];
    const int roof = fabsf(n[1]) > F(0.7);
    double t[3];
    face_tangent(n, t);
    const double q0 = (double) P[0] - o[0], q1 = (double) P[1] - o[1], q2 = (double) P[2] - o[2];
    const float u = (float) ((q0 * t[0] + q2 * t[2]) + q1 * t[1]);     /* einsum's float64 order */
    const float h = (float) (o[1] - (double) P[1]);
    const float col = floorf(u / su), fu = u - col * su;
    const float flo = floorf(h / fh), fv = h - flo * fh;
    const float dx = fabsf(fu - su / 2.0f);
    const int upper = flo >= 1.0f && !roof;
    const int inwin = dx < ww / 2.0f && fv > F(0.9) && fv < F(0.9) + wh && upper;
    const int shop = (flags & 4) > 0 && !roof;
    const float um = np_modf(u, F(2.5));
    const int store = shop && h > F(0.45) && h < F(3.1) && um > F(0.12) && um < F(2.38);
    const int is_glass = inwin && hash3(seed_hash(seed + 61), uo, f2u(col), f2u(flo)) < F(T->glass_fraction);
    const int glass = is_glass || store, curtain = inwin && !is_glass, brick = (flags & 2) > 0;
    *rf = glass ? F(0.05) : (brick ? F(0.28) : F(0.40));
    if (curtain) *rf = F(0.15);
    *mir = glass ? F(0.9) : (curtain ? F(0.25) : 0.0f);
    *gl = (uint8_t) glass;
    if (lidar) return;
    const float *color = T->obj_color + 3 * oid;
    const int wall = !roof && !inwin && !glass;
    if (wall && brick) {
        const float row = floorf(h / F(0.075));
        const float off = np_modf(row, 2.0f) * F(0.125);
        const float bcol = floorf((u + off) / F(0.25));
        const int mortar = (h - row * F(0.075)) < F(0.012) || (u + off - bcol * F(0.25)) < F(0.015);
        const float bvar = F(0.8) + F(0.4) * hash3(seed_hash(seed + 62), f2u(row), f2u(bcol), uo);
        if (mortar) set3(a, F(0.62), F(0.60), F(0.56));
        else set3(a, color[0] * bvar, color[1] * bvar, color[2] * bvar);
    }
    if (wall && !brick) {
        const float pl = F(0.92) + F(0.14) * vnoise(seed_hash(seed + 63), u, h, F(1.0 / 1.2))
                         - F(0.10) * vnoise(seed_hash(seed + 64), u, h * F(0.15), F(1.0 / 1.5));
        set3(a, color[0] * pl, color[1] * pl, color[2] * pl);
    }
    const int inframe = dx < ww / 2.0f + F(0.09) && fv > F(0.81) && fv < F(0.99) + wh && upper && !inwin;
    const int store_frame = shop && h > F(0.35) && h < F(3.2) && !store;
    if (wall && h < F(0.6)) set3(a, color[0] * F(0.55), color[1] * F(0.55), color[2] * F(0.55));
    if (curtain) {
        const float b = F(0.35) + F(0.3) * hash3(seed_hash(seed + 65), uo, f2u(col), f2u(flo));
        set3(a, b * F(0.9), b * F(0.85), b * F(0.75));
    }
    if (glass) set3(a, F(0.04), F(0.05), F(0.055));
    if ((inframe || store_frame) && !roof) set3(a, F(0.80), F(0.80), F(0.78));
    if (roof) {
        const float b = F(0.25) + F(0.1) * vnoise(seed_hash(seed + 66), P[0], P[2], F(1.0 / 2.0));
        set3(a, b * F(1.0), b * F(0.95), b * F(0.92));
    }
}

static inline float mean3(const float *c) { return (c[0] + c[1] + c[2]) / 3.0f; }

/* materials._vehicle_detail: painted details of a share of the vehicles on their paint albedo a (camera) */
static void vehicle_detail(const town_t *T, int64_t prim, const float *P, const float *n, float *a)
{
    static const double STRIPE[4][3] = {{0.85, 0.85, 0.82}, {0.80, 0.65, 0.10}, {0.60, 0.08, 0.06}, {0.05, 0.05, 0.05}};
    const int64_t seed = T->seed, oid = obj_index(T, prim);
    const uint32_t uo = (uint32_t) T->tri_obj[prim];
    if (!(hash2(seed_hash(seed + 71), uo, 0u) < F(T->vehicle_detail))) return;
    const double *o = T->obj_origin + 3 * oid;
    const float *prm = T->obj_params + 4 * oid;
    const float fx = prm[0], fz = prm[1], L = prm[2], W = prm[3];
    const double q0 = (double) P[0] - o[0], q2 = (double) P[2] - o[2];
    const float al = (float) (q0 * (double) fx + q2 * (double) fz);
    const float ac = (float) (q0 * (double) fz - q2 * (double) fx);
    const float h = (float) (o[1] - (double) P[1]);
    const float nf = n[0] * fx + n[2] * fz;
    const int end = fabsf(nf) > F(0.7);
    const int side = fabsf(nf) < F(0.3) && fabsf(n[1]) < F(0.5);
    const int32_t flags = T->obj_flags[oid];
    const float base[3] = {a[0], a[1], a[2]};
    float g = h / F(0.7);
    g = g < 1.0f ? g : 1.0f;
    float k = (F(0.72) + F(0.28) * g) * (F(0.9) + F(0.2) * vnoise(seed_hash(seed + 72), al + ac, h, F(1.0 / 0.3)));
    k = k + F(0.08) * (cell(seed_hash(seed + 73), al + ac, h, F(1.0 / 0.04)) - F(0.5));
    for (int c = 0; c < 3; ++c) a[c] = base[c] * k;
    const float h0 = F(0.5) + F(1.5) * hash2(seed_hash(seed + 75), uo, 0u);
    if (side && hash2(seed_hash(seed + 74), uo, 0u) < F(0.5) && h > h0
        && h < h0 + (F(0.08) + F(0.25) * hash2(seed_hash(seed + 76), uo, 0u))) {
        const int pal = (int) floorf(F(4.0) * hash2(seed_hash(seed + 77), uo, 0u));
        set3(a, F(STRIPE[pal][0]), F(STRIPE[pal][1]), F(STRIPE[pal][2]));
    }
    if (side && (flags & (8 | 16)) && np_modf(al, F(1.0) + F(1.5) * hash2(seed_hash(seed + 78), uo, 0u)) < F(0.03))
        for (int c = 0; c < 3; ++c) a[c] = a[c] * F(0.4);
    const int glyph = cell(seed_hash(seed + 80), al, h, F(1.0 / 0.09)) > F(0.55)
                      && cell(seed_hash(seed + 81), al, h, F(1.0 / 0.27)) > F(0.3);
    if (side && (flags & 16) && hash2(seed_hash(seed + 79), uo, 0u) < F(0.6) && h > F(1.4) && h < F(2.4)
        && al > F(-0.5) * L + F(1.0) && al < 0.0f && glyph) {
        const float ink = mean3(base) > F(0.4) ? F(0.08) : F(0.85);
        set3(a, ink, ink, ink);
    }
    if (end && h > F(0.25) && h < F(0.42))
        for (int c = 0; c < 3; ++c) a[c] = a[c] * F(0.35);
    const float aac = fabsf(ac);
    if (end && aac < F(0.26) && h > F(0.42) && h < F(0.54)) set3(a, F(0.85), F(0.85), F(0.80));
    if (end && aac < F(0.22) && h > F(0.45) && h < F(0.51) && cell(seed_hash(seed + 82), ac, h, F(1.0 / 0.04)) > F(0.5))
        set3(a, F(0.08), F(0.08), F(0.08));
    if (end && aac > F(0.5) * W - F(0.32) && h > F(0.75) && h < F(0.98)) {
        if (nf < 0.0f) set3(a, F(0.55), F(0.06), F(0.05));
        else set3(a, F(0.80), F(0.80), F(0.78));
    }
}

/* materials.surface for n hits; track: the road hits' tyre-track term in syn_road_l's order (camera only) */
void syn_surface(const town_t *T, int64_t n, const float *p, const float *nrm, const int64_t *prim,
                 const float *uvs, int lidar, const float *track, float *alb, float *mirror, float *refl,
                 uint8_t *glass, uint8_t *region)
{
    const int64_t seed = T->seed;
    int64_t k_road = 0;
    for (int64_t i = 0; i < n; ++i) {
        const float *P = p + 3 * i, *N = nrm + 3 * i;
        const float x = P[0], y = P[1], z = P[2];
        const int m = T->tri_mat[prim[i]];
        float a[3] = {0.0f, 0.0f, 0.0f}, mir = 0.0f, rf = F(0.3);
        uint8_t gl = 0, reg = 255;
        if (m == MAT_GROUND) {
            ground(T, prim[i], uvs + 2 * i, P, lidar, track, &k_road, a, &rf, &reg);
        } else if (m == MAT_FACADE) {
            facade(T, prim[i], P, N, lidar, a, &mir, &rf, &gl);
        } else if (lidar) {
            rf = F(lidar_refl(m));
            if (m == MAT_CAR_PAINT) {
                const int64_t oid = obj_index(T, prim[i]);
                rf = (T->obj_flags[oid] & 1) ? F(0.012) : F(0.18) + F(0.45) * mean3(T->obj_color + 3 * oid);
            } else if (m == MAT_CAR_GLASS) {
                gl = 1;
            }
        } else if (m == MAT_CURB) {
            const float f0 = vnoise(seed_hash(seed + 11), x + z, y, F(1.0 / (0.4 / 1)));
            const float f1 = vnoise(seed_hash(seed + 11 + 101), x + z, y, F(1.0 / (0.4 / 2)));
            const float fbm = (0.0f + F(1.0) * f0 + F(0.5) * f1) / F(1.5);
            const float g = F(0.52) + F(0.10) * fbm
                            + F(0.05) * (cell(seed_hash(seed + 12), x + z, y, F(1.0 / 0.03)) - F(0.5));
            set3(a, g * F(1.0), g * F(0.99), g * F(0.96));
            rf = F(0.35);
        } else if (m == MAT_CAR_PAINT) {
            const int64_t oid = obj_index(T, prim[i]);
            const int black = (T->obj_flags[oid] & 1) > 0;
            const float *c0 = T->obj_color + 3 * oid;
            const float k = F(0.97) + F(0.06) * cell(seed_hash(seed + 21), x + y, z, F(1.0 / 0.5));
            set3(a, c0[0] * k, c0[1] * k, c0[2] * k);
            mir = black ? F(0.10) : F(0.07);
            rf = black ? F(0.012) : F(0.18) + F(0.45) * mean3(a);
            if (T->vehicle_detail > 0.0) vehicle_detail(T, prim[i], P, N, a);   /* camera only; rf of the paint */
        } else if (m == MAT_CAR_GLASS) {
            set3(a, F(0.03), F(0.035), F(0.04));
            mir = F(0.55); rf = F(0.05); gl = 1;
        } else if (m == MAT_TYRE) {
            set3(a, F(0.05), F(0.05), F(0.05));
            rf = F(0.10);
        } else if (m == MAT_TRUNK) {
            const float b = F(0.8) + F(0.4) * vnoise(seed_hash(seed + 31), x + z, y, F(1.0 / 0.15));
            set3(a, b * F(0.26), b * F(0.19), b * F(0.13));
            rf = F(0.30);
        } else if (m == MAT_FOLIAGE) {
            const float *c0 = T->obj_color + 3 * obj_index(T, prim[i]);
            const float leaf = hash3(seed_hash(seed + 41), f2u(floorf(x / F(0.25))), f2u(floorf(y / F(0.25))),
                                     f2u(floorf(z / F(0.25))));
            const float blotch = vnoise(seed_hash(seed + 42), x + F(0.7) * y, z - F(0.5) * y, F(1.0 / 0.8));
            const float k = F(0.55) + F(0.6) * leaf + F(0.3) * blotch;
            set3(a, c0[0] * k, c0[1] * k, c0[2] * k);
            rf = F(0.40);
        } else if (m == MAT_METAL) {
            const float *c0 = T->obj_color + 3 * obj_index(T, prim[i]);
            set3(a, c0[0], c0[1], c0[2]);
            mir = F(0.05); rf = F(0.45);
        } else if (m == MAT_FENCE) {
            const int64_t oid = obj_index(T, prim[i]);
            const float *c0 = T->obj_color + 3 * oid;
            double t[3];
            face_tangent(N, t);
            const double u = ((double) x * t[0] + (double) z * t[2]) + (double) y * t[1];
            const double plank = floor(u / 0.16);
            const int gap = (u - plank * 0.16) < 0.02;
            const float k = F(0.85) + F(0.3) * hash2(seed_hash(seed + 51), d2u(plank), (uint32_t) T->tri_obj[prim[i]]);
            const float w = 1.0f - F(0.1) * vnoise(seed_hash(seed + 52), (float) u, y, F(1.0 / 0.3));
            for (int c = 0; c < 3; ++c) {
                const float v = c0[c] * k * w;
                a[c] = gap ? v * F(0.35) : v;
            }
            rf = F(0.30);
        } else if (m == MAT_LAMP) {
            set3(a, F(0.85), F(0.85), F(0.80));
            rf = F(0.60);
        }
        for (int c = 0; c < 3; ++c) alb[3 * i + c] = clip01(a[c]);
        mirror[i] = mir; refl[i] = rf; glass[i] = gl; region[i] = reg;
    }
}

/* ---- camera.py ---- */
static inline float dot3(const float *a, const float *b) { return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]; }

/* render: world directions of the camera rays (cam_dirs rotated by R, 3x3 row-major) and the ray buffer
   [origin | direction] open3d casts */
void syn_cam_rays(int64_t n, const float *cdirs, const float *R, const float *o, float *dirs, float *rays)
{
    for (int64_t i = 0; i < n; ++i) {
        const float *c = cdirs + 3 * i;
        for (int j = 0; j < 3; ++j) {
            const float d = c[0] * R[3 * j] + c[1] * R[3 * j + 1] + c[2] * R[3 * j + 2];
            dirs[3 * i + j] = d;
            rays[6 * i + j] = o[j];
            rays[6 * i + 3 + j] = d;
        }
    }
}

/* shade, lidar.scan: split cast results into hits (t < far) and misses; per hit its direction, distance,
   point, normal (turned to face the ray if face_ray), triangle and uv; t_out = t with inf for misses,
   mat_out = material (0 for misses).
   Origins advance by o_stride floats per ray (0 = one origin). Returns the number of hits. */
int64_t syn_hits(const town_t *T, int64_t n, const float *t_hit, const uint32_t *prim_ids, const float *uvs_in,
                 const float *nrm_in, const float *dirs, const float *origins, int64_t o_stride, double far,
                 int face_ray, float *t_out, uint8_t *mat_out, int64_t *idx, float *d, float *th, float *p, float *nrm,
                 int64_t *prim, float *uvs, int64_t *miss, int64_t *n_miss)
{
    int64_t k = 0, m = 0;
    for (int64_t i = 0; i < n; ++i) {
        const float t = t_hit[i];
        if (!(isfinite(t) && t < F(far))) {
            t_out[i] = INFINITY; mat_out[i] = 0; miss[m++] = i;
            continue;
        }
        const float *di = dirs + 3 * i, *o = origins + o_stride * i, *ni = nrm_in + 3 * i;
        t_out[i] = t;
        idx[k] = i; th[k] = t; prim[k] = prim_ids[i];
        mat_out[i] = T->tri_mat[prim_ids[i]];
        uvs[2 * k] = uvs_in[2 * i]; uvs[2 * k + 1] = uvs_in[2 * i + 1];
        const int flip = face_ray && dot3(ni, di) > 0.0f;
        for (int j = 0; j < 3; ++j) {
            d[3 * k + j] = di[j];
            p[3 * k + j] = o[j] + t * di[j];
            nrm[3 * k + j] = flip ? -ni[j] : ni[j];
        }
        ++k;
    }
    *n_miss = m;
    return k;
}

/* shade: bumpy foliage normals (in place) */
void syn_bump(const town_t *T, int64_t k, const float *p, const int64_t *prim, float *nrm)
{
    const uint32_t h[3] = {seed_hash(T->seed + 71), seed_hash(T->seed + 72), seed_hash(T->seed + 73)};
    for (int64_t i = 0; i < k; ++i) {
        if (T->tri_mat[prim[i]] != MAT_FOLIAGE) continue;
        const float *P = p + 3 * i;
        float *N = nrm + 3 * i;
        const uint32_t q0 = f2u(floorf(P[0] / F(0.2))), q1 = f2u(floorf(P[1] / F(0.2))),
                       q2 = f2u(floorf(P[2] / F(0.2)));
        float nf[3];
        for (int j = 0; j < 3; ++j) nf[j] = N[j] + F(1.2) * (hash3(h[j], q0, q1, q2) - F(0.5));
        const float nm = sqrtf(nf[0] * nf[0] + nf[1] * nf[1] + nf[2] * nf[2]);
        for (int j = 0; j < 3; ++j) N[j] = nf[j] / nm;
    }
}

/* shade: shadow rays from the lit hits (ndl > 0) towards the sun; returns their number */
int64_t syn_shadow_rays(int64_t k, const float *p, const float *nrm, const float *ndl, const float *sun,
                        int64_t *li, float *rays)
{
    int64_t m = 0;
    for (int64_t i = 0; i < k; ++i) {
        if (!(ndl[i] > 0.0f)) continue;
        li[m] = i;
        for (int j = 0; j < 3; ++j) {
            rays[6 * m + j] = p[3 * i + j] + nrm[3 * i + j] * F(0.03);
            rays[6 * m + 3 + j] = sun[j];
        }
        ++m;
    }
    return m;
}

/* shade: direct light c = albedo (x gain) * (ambient + sun); with bounce, per mirror hit (mirror > 0)
   the highlight's clipped cosine (specbase, to the 60th power in numpy), 1 - |cos i| (omc, to the 5th),
   the reflected direction, and for traced ones (mirror >= 0.5) the reflected ray [p + 0.03 n | rdir].
   Returns the number of mirror hits; *n_traced the traced ones (indices into the mirror hits). */
int64_t syn_light(const town_t *T, int64_t k, const int64_t *prim, const float *d, const float *nrm,
                  const float *p, const float *ndl, const float *alb, const float *mirror, const float *gain,
                  const float *ambient, const float *sun_color, const float *sun, int bounce, float *c,
                  int64_t *mi, float *specbase, float *omc, float *rdir, int64_t *traced, float *trays,
                  int64_t *n_traced)
{
    int64_t m = 0, nt = 0;
    for (int64_t i = 0; i < k; ++i) {
        const float *N = nrm + 3 * i, *D = d + 3 * i;
        float up = -N[1];
        if (!isnan(up)) up = up > -1.0f ? up : -1.0f;
        if (!isnan(up)) up = up < 1.0f ? up : 1.0f;
        const float w = F(0.65) + F(0.35) * up;
        const float *g = gain ? gain + 3 * T->tri_mat[prim[i]] : 0;
        for (int j = 0; j < 3; ++j) {
            const float a = g ? alb[3 * i + j] * g[j] : alb[3 * i + j];
            c[3 * i + j] = a * (ambient[j] * w + sun_color[j] * ndl[i]);
        }
        if (!bounce || !(mirror[i] > 0.0f)) continue;
        float h[3] = {sun[0] - D[0], sun[1] - D[1], sun[2] - D[2]};
        const float hn = sqrtf(h[0] * h[0] + h[1] * h[1] + h[2] * h[2]);
        h[0] /= hn; h[1] /= hn; h[2] /= hn;
        specbase[m] = clip01(dot3(N, h));
        const float dn = dot3(D, N);
        omc[m] = 1.0f - fabsf(dn);
        for (int j = 0; j < 3; ++j) rdir[3 * m + j] = D[j] - 2.0f * dn * N[j];
        mi[m] = i;
        if (mirror[i] >= F(0.5)) {
            traced[nt] = m;
            for (int j = 0; j < 3; ++j) {
                trays[6 * nt + j] = p[3 * i + j] + N[j] * F(0.03);
                trays[6 * nt + 3 + j] = rdir[3 * m + j];
            }
            ++nt;
        }
        ++m;
    }
    *n_traced = nt;
    return m;
}

/* shade: highlight and Fresnel-weighted reflection on the mirror hits, then haze; writes col[idx[i]] */
void syn_final(int64_t k, float *c, int64_t m, const int64_t *mi, const float *spec60, const float *ndl,
               const float *f5, const float *mirror, const float *rcol, const float *tr, const float *horizon,
               const int64_t *idx, float *col)
{
    for (int64_t j = 0; j < m; ++j) {
        const int64_t i = mi[j];
        const float spec = spec60[j] * (ndl[i] > 0.0f ? 1.0f : 0.0f);
        const float fres = mirror[i] * (F(0.25) + F(0.75) * f5[j]);
        for (int q = 0; q < 3; ++q) {
            const float v = c[3 * i + q] + F(1.5) * spec;
            c[3 * i + q] = v * (1.0f - fres) + rcol[3 * j + q] * fres;
        }
    }
    for (int64_t i = 0; i < k; ++i)
        for (int q = 0; q < 3; ++q)
            col[3 * idx[i] + q] = c[3 * i + q] * tr[i] + horizon[q] * (1.0f - tr[i]);
}

/* render: z-depth from the hit distance (0 = sky or beyond max_depth) */
void syn_depth(int64_t n, const float *t, const float *zfac, double max_depth, float *depth)
{
    for (int64_t i = 0; i < n; ++i) {
        const float v = isfinite(t[i]) ? t[i] * zfac[i] : 0.0f;
        depth[i] = v > F(max_depth) ? 0.0f : v;
    }
}

/* render: vignetting (per pixel), shot + read noise, 8-bit quantisation of the blurred image (n pixels) */
void syn_sensor(int64_t n, const float *img, const float *vignette, const float *noise, uint8_t *rgb)
{
    for (int64_t i = 0; i < n; ++i) {
        for (int q = 0; q < 3; ++q) {
            float v = img[3 * i + q] * vignette[i];
            v = v + noise[3 * i + q] * (F(0.006) + F(0.012) * sqrtf(clip01(v)));
            v = v * 255.0f + F(0.5);
            if (!isnan(v)) v = v > 0.0f ? v : 0.0f;
            if (!isnan(v)) v = v < 255.0f ? v : 255.0f;
            rgb[3 * i + q] = (uint8_t) v;
        }
    }
}

/* ---- lidar.py ---- */
/* the hits not lost at glass: cos of incidence and return probability, compacted (idx, t, refl, cosi, p_ret);
   returns their number */
int64_t syn_lidar_returns(int64_t k, const uint8_t *lost, const int64_t *idx, const float *t, const float *d,
                          const float *nrm, const float *refl, double max_range, int64_t *idx_out, float *t_out,
                          float *refl_out, float *cosi_out)
{
    int64_t m = 0;
    for (int64_t i = 0; i < k; ++i) {
        if (lost[i]) continue;
        idx_out[m] = idx[i]; t_out[m] = t[i]; refl_out[m] = refl[i];
        cosi_out[m] = fabsf(dot3(nrm + 3 * i, d + 3 * i));
        ++m;
    }
    return m;
}

/* p_ret of the candidate returns: reflectance, incidence and range falloff */
void syn_lidar_p_ret(int64_t m, const float *t, const float *refl, const float *cosi, double max_range, float *p_ret)
{
    for (int64_t i = 0; i < m; ++i) {
        const float r = refl[i];
        float p = clipf(r * F(12.0), 0.0f, 1.0f) * clipf(cosi[i] * F(8.0), 0.0f, 1.0f) * F(0.995);
        const float q = t[i] / F(max_range);
        const float rm = (r >= F(0.01) || isnan(r)) ? r : F(0.01);
        p *= clipf(F(1.3) - q * q * (F(0.15) / rm), 0.0f, 1.0f);
        p_ret[i] = p;
    }
}

/* the kept returns as (x, y, z, reflectance) in the velodyne frame, with range and intensity noise;
   returns their number */
int64_t syn_lidar_points(int64_t m, const uint8_t *keep, const int64_t *idx, const float *t, const float *refl,
                         const float *cosi, const float *noise_r, const float *noise_i, const float *dirs_velo,
                         float *pts)
{
    int64_t j = 0;
    for (int64_t i = 0; i < m; ++i) {
        if (!keep[i]) continue;
        const float r = t[i] + noise_r[j];
        const float inten = clipf(refl[i] * (F(0.55) + F(0.45) * cosi[i]) + noise_i[j], 0.0f, F(0.99));
        const float *dv = dirs_velo + 3 * idx[i];
        pts[4 * j] = dv[0] * r; pts[4 * j + 1] = dv[1] * r; pts[4 * j + 2] = dv[2] * r; pts[4 * j + 3] = inten;
        ++j;
    }
    return j;
}

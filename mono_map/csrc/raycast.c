/* Ray casting into an OctoMap key box and the map's log-odds mirror (mono_map.mapping.raycast_c loads it).

   OctoMap 1.10's computeRayKeys transcribed with the same types (float points and direction, double
   tMax/tDelta), emitting linear box indices; the distribution integration's per-ray weights; the
   per-frame accumulators; the log-odds mirror's block table and clamped updates; .ot node I/O.
   Built with -ffp-contract=off and no -ffast-math (mono_map/ckernel.py): IEEE arithmetic, as in
   OctoMap's own build, so the cells and values are those of the numpy paths (tests check both). */
#include <math.h>
#include <float.h>
#include <stdint.h>
#include <string.h>
#include <stdlib.h>

/* computeRayKeys' set-up for the ray origin -> e: steps, tMax, tDelta (OctoMap's types); returns the
   float length |e - origin|. */
/* linear index of key k in the box whose low corner is lo */
static inline int64_t box_index(const int64_t *k, const int64_t *lo, const int64_t *strides)
{
    return (k[0] - lo[0]) * strides[0] + (k[1] - lo[1]) * strides[1] + (k[2] - lo[2]) * strides[2];
}

static inline float dda_setup(const float *origin, const float *e, const int64_t *key_origin, double res,
                              int64_t tree_max_val, int *step, double *tMax, double *tDelta)
{
    float d[3] = {e[0] - origin[0], e[1] - origin[1], e[2] - origin[2]};
    float nsq = d[0] * d[0] + d[1] * d[1] + d[2] * d[2];
    float length = (float) sqrt((double) nsq);
    d[0] /= length; d[1] /= length; d[2] /= length;
    for (int a = 0; a < 3; ++a) {
        if (d[a] > 0.0) step[a] = 1;
        else if (d[a] < 0.0) step[a] = -1;
        else step[a] = 0;
        if (step[a] != 0) {
            double border = ((double) ((int) key_origin[a] - (int) tree_max_val) + 0.5) * res;
            border += (float) (step[a] * res * 0.5);
            tMax[a] = (border - (double) origin[a]) / (double) d[a];
            tDelta[a] = res / fabs((double) d[a]);
        } else {
            tMax[a] = DBL_MAX;
            tDelta[a] = DBL_MAX;
        }
    }
    return length;
}

/* computeRayKeys(origin, end) for n ends. With mark == NULL: writes the linear indices to out
   (the origin cell first for every ray that leaves it) and returns their number, or -1 if cap is
   too small. With mark (a bitmap of mark_size bytes over the box, 0 = not seen): writes each index
   whose mark is 0 (setting it to 1), so out holds the distinct unmarked cells; -2 if an index falls
   outside. Cells pre-marked (e.g. 2 = occupied this frame) are skipped. The mark is set with an atomic
   exchange, so several threads may share one bitmap: each cell is written by exactly one of them. */
#define EMIT(x) do { \
        if (mark) { \
            if ((uint64_t) (x) >= (uint64_t) mark_size) return -2; \
            if (!mark[(x)] && !__atomic_exchange_n(mark + (x), (uint8_t) 1, __ATOMIC_RELAXED)) { \
                if (off >= cap) return -1; \
                out[off++] = (x); \
            } \
        } else { \
            if (off >= cap) return -1; \
            out[off++] = (x); \
        } \
    } while (0)
static inline int64_t ray_cells(const float *origin, const int64_t *key_origin, const float *ends,
                                const int64_t *key_ends, int64_t n, double res, const int64_t *lo,
                                const int64_t *strides, int64_t tree_max_val, int64_t *out, int64_t cap,
                                uint8_t *mark, int64_t mark_size)
{
    int64_t off = 0;
    const int64_t lin_o = box_index(key_origin, lo, strides);
    for (int64_t i = 0; i < n; ++i) {
        const float *e = ends + 3 * i;
        const int64_t *ke = key_ends + 3 * i;
        if (ke[0] == key_origin[0] && ke[1] == key_origin[1] && ke[2] == key_origin[2])
            continue;
        EMIT(lin_o);
        int step[3];
        double tMax[3], tDelta[3];
        const float length = dda_setup(origin, e, key_origin, res, tree_max_val, step, tMax, tDelta);
        /* the DDA step on scalars (the compiler keeps them in registers): the axis whose border is nearest */
        const int64_t lin_end = box_index(ke, lo, strides);
        const int64_t d0 = step[0] * strides[0], d1 = step[1] * strides[1], d2 = step[2] * strides[2];
        double t0 = tMax[0], t1 = tMax[1], t2 = tMax[2];
        const double dt0 = tDelta[0], dt1 = tDelta[1], dt2 = tDelta[2], len = (double) length;
        int64_t lin = lin_o;
        for (;;) {
            if (t0 < t1) {
                if (t0 < t2) { lin += d0; t0 += dt0; } else { lin += d2; t2 += dt2; }
            } else if (t1 < t2) { lin += d1; t1 += dt1; } else { lin += d2; t2 += dt2; }
            if (lin == lin_end) break;
            double dist = t0 < t1 ? t0 : t1;
            dist = dist < t2 ? dist : t2;
            if (dist > len) break;
            EMIT(lin);
        }
    }
    return off;
}

/* the two modes compiled separately (the mode test leaves the inner loop) */
int64_t mm_ray_cells(const float *origin, const int64_t *key_origin, const float *ends,
                     const int64_t *key_ends, int64_t n, double res, const int64_t *lo,
                     const int64_t *strides, int64_t tree_max_val, int64_t *out, int64_t cap,
                     uint8_t *mark, int64_t mark_size)
{
    if (mark)
        return ray_cells(origin, key_origin, ends, key_ends, n, res, lo, strides, tree_max_val, out, cap, mark,
                         mark_size);
    return ray_cells(origin, key_origin, ends, key_ends, n, res, lo, strides, tree_max_val, out, cap, NULL, 0);
}

/* Distribution-weighted rays (see mono_map/mapping/distribution.py). Ray i visits the cells of
   computeRayKeys(origin, end_i) and, if has_end[i], the end cell. A cell entered at ray length
   t_in and left at t_out (metres; the end cell is left at max(t_out, |end - origin|)) covers depths
   [t_in, t_out] * scale[i] of the ray's piecewise-uniform depth distribution (probs p[i*K..], edges
   e[i*edge_stride..], K bins, p_beyond[i] beyond them). Its expected OctoMap update is
   dl = P(in)*hit + P(beyond)*miss; updates smaller than min_update in magnitude are dropped. Per cell, the rays combine as: the largest positive dl if any,
   else the most negative one. With acc (a zeroed float bitmap over the box, 0 = untouched): each
   cell's index is written to out the first time, acc holds the combined dl; returns the count.
   With acc == NULL: (index, dl) pairs with repeats into out / out_dl. -1: cap too small; -2: outside. */
static inline double cdf_at(double z, const float *p, const double *e, int64_t K, int64_t *k, double *cum)
{
    while (*k < K && z >= e[*k + 1]) { *cum += (double) p[*k]; ++*k; }
    double c = *cum;
    if (*k < K) {
        double w = e[*k + 1] - e[*k];
        if (w > 0.0 && z > e[*k]) c += (double) p[*k] * (z - e[*k]) / w;
    }
    return c;
}

/* Far depth of one piecewise-uniform distribution: the depth where P(beyond) = mass - CDF + p_beyond
   first falls below eps (linear within the bin), else the last edge; mass: the sum of p in bin order. */
static inline double far_depth_mass(const float *p, double mass, double pb, const double *e, int64_t K, double eps)
{
    double beyond = mass + pb;                   /* P(beyond) at the lower edge of bin j */
    for (int64_t j = 0; j < K; ++j) {
        double after = beyond - (double) p[j];
        if (after < eps) {
            double f = p[j] > 0.0f ? (beyond - eps) / (double) p[j] : 0.0;
            f = f < 0.0 ? 0.0 : (f > 1.0 ? 1.0 : f);
            return e[j] + (e[j + 1] - e[j]) * f;
        }
        beyond = after;
    }
    return e[K];
}

static inline double far_depth_one(const float *p, double pb, const double *e, int64_t K, double eps)
{
    double mass = 0.0;
    for (int64_t j = 0; j < K; ++j) mass += (double) p[j];
    return far_depth_mass(p, mass, pb, e, K, eps);
}

void mm_far_depth(const float *probs, const double *p_beyond, const double *edges, int64_t edge_stride,
                  int64_t K, int64_t n, double eps, double *out)
{
    for (int64_t i = 0; i < n; ++i)
        out[i] = far_depth_one(probs + K * i, p_beyond[i], edges + edge_stride * i, K, eps);
}

/* Rays' distributions in one pass (mono_map/mapping/distribution.py, ray_distributions): conditional bin
   probabilities q (n x K) at temperature T (inv_t = 1/T: q^(1/T) rescaled to the row's mass, rounded to
   float32, as apply_temperature), times (1 - p_beyond) (float32, as unconditional_mass) into out (n x K; may
   be q itself: element-wise), and each row's far depth (far_depth_one) into far. idx (n, or NULL): output row
   i reads q's row idx[i] (a gather without an intermediate copy). */
/* R rows of mm_ray_mass at once (R a constant where inlined: every per-row sum stays in bin order, and the
   R independent sums overlap in the pipeline instead of waiting for each other's additions) */
static inline __attribute__((always_inline)) void ray_mass_rows(const float *const *p, float *const *o, const double *pb, const double *const *e,
                                 int R, int64_t K, double inv_t, double eps, double *far)
{
    double keep[4], sp[4], sq[4], scale[4], mass[4];
    for (int r = 0; r < R; ++r) { keep[r] = 1.0 - pb[r]; sp[r] = 0.0; sq[r] = 0.0; mass[r] = 0.0; }
    if (inv_t == 1.0) {
        for (int64_t j = 0; j < K; ++j)
            for (int r = 0; r < R; ++r) {
                o[r][j] = (float) ((double) p[r][j] * keep[r]);
                mass[r] += (double) o[r][j];
            }
    } else {
        for (int64_t j = 0; j < K; ++j)
            for (int r = 0; r < R; ++r) {
                double x = (double) p[r][j];
                sp[r] += x;
                sq[r] += inv_t == 2.0 ? x * x : pow(x, inv_t);
            }
        for (int r = 0; r < R; ++r) scale[r] = sp[r] / (sq[r] > 0.0 ? sq[r] : 1.0);
        for (int64_t j = 0; j < K; ++j)             /* the tempered values again (a square: cheap) */
            for (int r = 0; r < R; ++r) {
                double x = (double) p[r][j];
                double t = inv_t == 2.0 ? x * x : pow(x, inv_t);
                o[r][j] = (float) ((double) (float) (t * scale[r]) * keep[r]);
                mass[r] += (double) o[r][j];
            }
    }
    /* far_depth_mass of the R rows, stepped together */
    double beyond[4];
    int done[4], left = R;
    for (int r = 0; r < R; ++r) { beyond[r] = mass[r] + pb[r]; done[r] = 0; }
    for (int64_t j = 0; j < K && left > 0; ++j)
        for (int r = 0; r < R; ++r) {
            if (done[r]) continue;
            const float *pr = o[r];
            double after = beyond[r] - (double) pr[j];
            if (after < eps) {
                double f = pr[j] > 0.0f ? (beyond[r] - eps) / (double) pr[j] : 0.0;
                f = f < 0.0 ? 0.0 : (f > 1.0 ? 1.0 : f);
                far[r] = e[r][j] + (e[r][j + 1] - e[r][j]) * f;
                done[r] = 1;
                --left;
            } else beyond[r] = after;
        }
    for (int r = 0; r < R; ++r) if (!done[r]) far[r] = e[r][K];
}

void mm_ray_mass(const float *q, const double *p_beyond, int64_t n, int64_t K, double inv_t, const double *edges,
                 int64_t edge_stride, double eps, float *out, double *far, const int64_t *idx)
{
    int64_t i = 0;
    for (; i < n; i += 4) {
        const int R = n - i < 4 ? (int) (n - i) : 4;
        const float *p[4];
        float *o[4];
        const double *e[4];
        for (int r = 0; r < R; ++r) {
            p[r] = q + K * (idx ? idx[i + r] : i + r);
            o[r] = out + K * (i + r);
            e[r] = edges + edge_stride * (i + r);
        }
        if (R == 4) ray_mass_rows(p, o, p_beyond + i, e, 4, K, inv_t, eps, far + i);
        else for (int r = 0; r < R; ++r) ray_mass_rows(p + r, o + r, p_beyond + i + r, e + r, 1, K, inv_t, eps, far + i + r);
    }
}

/* Validation sums of n distributions (distribution.check_distribution): counts of non-finite and of negative
   values in probs (n x K) and p_beyond (n), their minima, and the largest row total sum(probs) + p_beyond.
   stats: [bad_p, neg_p, min_p, bad_b, neg_b, min_b, max_total]; counts over row totals above tol in *n_over.
   row_mass (n, or NULL): each row's sum of its finite probs in bin order (mm_ray_weights' per-ray mass). */
void mm_check_rows(const float *probs, const double *p_beyond, int64_t n, int64_t K, double tol, double *stats,
                   int64_t *n_over, double *row_mass)
{
    int64_t bad_p = 0, neg_p = 0, bad_b = 0, neg_b = 0, over = 0;
    double min_p = DBL_MAX, min_b = DBL_MAX, max_total = -DBL_MAX;
    for (int64_t i = 0; i < n; i += 4) {          /* 4 rows at a time, each row's total in bin order */
        const int R = n - i < 4 ? (int) (n - i) : 4;
        double total[4] = {0.0, 0.0, 0.0, 0.0};
        for (int64_t j = 0; j < K; ++j)
            for (int r = 0; r < R; ++r) {
                float x = probs[K * (i + r) + j];
                if (!isfinite(x)) { ++bad_p; continue; }
                if (x < 0.0f) { ++neg_p; }
                if ((double) x < min_p) min_p = (double) x;
                total[r] += (double) x;
            }
        for (int r = 0; r < R; ++r) {
            if (row_mass) row_mass[i + r] = total[r];
            double b = p_beyond[i + r];
            if (!isfinite(b)) ++bad_b;
            else {
                if (b < 0.0) ++neg_b;
                if (b < min_b) min_b = b;
                total[r] += b;
            }
            if (total[r] > max_total) max_total = total[r];
            if (total[r] > tol) ++over;
        }
    }
    stats[0] = (double) bad_p; stats[1] = (double) neg_p; stats[2] = min_p;
    stats[3] = (double) bad_b; stats[4] = (double) neg_b; stats[5] = min_b; stats[6] = max_total;
    *n_over = over;
}

/* The per-cell combination of several rays' updates v (each kept only if v != 0 and |v| >= min_update):
   the largest positive if any, else the most negative. */
#define COMBINE(best, v) do { float w_ = (v); if (w_ != 0.0f && fabsf(w_) >= min_update && \
        ((best) == 0.0f || (w_ > 0.0f ? ((best) < 0.0f || w_ > (best)) : ((best) < 0.0f && w_ < (best))))) \
        (best) = w_; } while (0)
#define COMBINE_ANY(best, w_) do { if ((best) == 0.0f || ((w_) > 0.0f ? ((best) < 0.0f || (w_) > (best)) : \
        ((best) < 0.0f && (w_) < (best)))) (best) = (w_); } while (0)          /* the same rule, no filter */
#define PUT(x, v) do { float v_ = (v); if (v_ != 0.0f) { if ((x) < 0 || (x) >= acc_size) { ret = -2; goto done; } \
        if (acc) { float o_ = acc[(x)]; \
            if (o_ == 0.0f) { if (off >= cap) { ret = -1; goto done; } acc[(x)] = v_; out[off++] = (x); } \
            else if (v_ > 0.0f ? (o_ < 0.0f || v_ > o_) : (o_ < 0.0f && v_ < o_)) acc[(x)] = v_; } \
        else { if (off >= cap) { ret = -1; goto done; } out_dl[off] = v_; out[off++] = (x); } } } while (0)
/* PUT(x, miss) for the most negative possible update (a whole miss: it replaces any negative, never a positive) */
#define PUT_MISS(x) do { if ((x) < 0 || (x) >= acc_size) { ret = -2; goto done; } \
        if (acc) { float o_ = acc[(x)]; \
            if (o_ == 0.0f) { if (off >= cap) { ret = -1; goto done; } acc[(x)] = miss; out[off++] = (x); } \
            else if (o_ < 0.0f && miss < o_) acc[(x)] = miss; } \
        else { if (off >= cap) { ret = -1; goto done; } out_dl[off] = miss; out[off++] = (x); } } while (0)
typedef struct { const float *p; const double *e; double sc, pb, mass, cum, c_in, c_out, z_sure; int64_t k; int sure; } RayState;
typedef struct { double t; int64_t j; } SortKey;
static int cmp_sort_key(const void *a, const void *b)
{
    double x = ((const SortKey *) a)->t, y = ((const SortKey *) b)->t;
    return x < y ? -1 : (x > y ? 1 : 0);
}
/* The depth below which a ray's update is surely <= thr (its free-space update then snaps to a whole miss;
   see mono_map/mapping/distribution.py, snap_threshold): every cell ending before it has
   dl <= c_out * hit + (mass + pb - c_out) * miss <= thr, i.e. CDF c_out <= C. Margins of 1e-9 (relative)
   cover the rounding of the CDF; -1 (never) when C < 0. */
static inline double sure_free_depth(const float *p, const double *e, int64_t K, double mass, double pb, double hit,
                                     double miss, double thr)
{
    double C = (thr - (mass + pb) * miss) / (hit - miss) - 1e-9, cum = 0.0;
    if (C < 0.0) return -1.0;
    for (int64_t b = 0; b < K; ++b) {
        double pb_ = (double) p[b];
        if (cum + pb_ > C) {
            double w = e[b + 1] - e[b];
            double z = (w > 0.0 && pb_ > 0.0) ? e[b] + (C - cum) / pb_ * w : e[b];
            return z * (1.0 - 1e-9);
        }
        cum += pb_;
    }
    return DBL_MAX;
}
/* Rays are walked in groups sharing one end cell (and so one end point, the cell's centre, and one DDA cell
   sequence): groups[g] .. groups[g + 1] - 1 index order[], which holds the rays' rows (ends, key_ends and
   has_end are read from the group's first ray). Each cell of the walk gets the combination of the group's
   rays' updates, so the walk and the memory traffic are paid once per group. */
int64_t mm_ray_weights(const float *origin, const int64_t *key_origin, const float *ends,
                       const int64_t *key_ends, const uint8_t *has_end, const double *scale,
                       const int64_t *order, const int64_t *groups, int64_t n_groups,
                       const float *probs, const double *p_beyond, const double *edges, int64_t edge_stride,
                       int64_t K, float hit, float miss, float min_update, double res, const int64_t *lo, const int64_t *strides,
                       int64_t tree_max_val, float *acc, int64_t acc_size, int64_t *out, float *out_dl,
                       int64_t cap, int snap, float thr, const double *ray_mass)
{
    int64_t off = 0, ret = 0, max_group = 0;
    for (int64_t g = 0; g < n_groups; ++g)
        if (groups[g + 1] - groups[g] > max_group) max_group = groups[g + 1] - groups[g];
    const size_t mg = (size_t) (max_group > 0 ? max_group : 1);
    RayState *st = (RayState *) malloc(sizeof(RayState) * mg);
    int64_t *act = (int64_t *) malloc(sizeof(int64_t) * mg);
    SortKey *sk = (SortKey *) malloc(sizeof(SortKey) * mg);
    if (!st || !act || !sk) { free(st); free(act); free(sk); return -3; }
    const int64_t lin_o = box_index(key_origin, lo, strides);
    const double dhit = (double) hit, dmiss = (double) miss;
    for (int64_t g = 0; g < n_groups; ++g) {
        const int64_t first = order[groups[g]], m = groups[g + 1] - groups[g];
        const float *e = ends + 3 * first;
        const int64_t *ke = key_ends + 3 * first;
        const int end_ok = has_end[first];
        for (int64_t j = 0; j < m; ++j) {
            const int64_t i = order[groups[g] + j];
            RayState *r = st + j;
            r->p = probs + K * i;
            r->e = edges + edge_stride * i;
            r->sc = scale[i];
            r->pb = p_beyond[i];
            double mass = 0.0;      /* the sum of its bins in bin order (given by the caller, or summed here) */
            if (ray_mass) mass = ray_mass[i];
            else for (int64_t b = 0; b < K; ++b) mass += (double) r->p[b];
            r->mass = mass;
            r->k = 0;
            r->cum = 0.0;
            r->c_in = cdf_at(0.0, r->p, r->e, K, &r->k, &r->cum);
            r->z_sure = snap ? sure_free_depth(r->p, r->e, K, mass, r->pb, dhit, dmiss, (double) thr) : -1.0;
            r->sure = r->z_sure > 0.0;
        }
        if (ke[0] == key_origin[0] && ke[1] == key_origin[1] && ke[2] == key_origin[2]) {
            /* empty rays: only the end cell, holding all the mass */
            if (end_ok) {
                float best = 0.0f;
                for (int64_t j = 0; j < m; ++j)
                    COMBINE(best, (float) ((st[j].mass - st[j].c_in) * dhit + st[j].pb * dmiss));
                PUT(lin_o, best);
            }
            continue;
        }
        int step[3];
        double tMax[3], tDelta[3];
        const float length = dda_setup(origin, e, key_origin, res, tree_max_val, step, tMax, tDelta);
        int64_t lin = lin_o;
        const int64_t lin_end = box_index(ke, lo, strides);
        /* the DDA step on scalars (the compiler keeps them in registers): the axis whose border is nearest */
        const int64_t d0 = step[0] * strides[0], d1 = step[1] * strides[1], d2 = step[2] * strides[2];
        double t0 = tMax[0], t1 = tMax[1], t2 = tMax[2];
        const double dt0 = tDelta[0], dt1 = tDelta[1], dt2 = tDelta[2], len = (double) length;
        double t_out = fmin(fmin(t0, t1), t2), t_in = 0.0;
        int64_t cell = lin_o;            /* the cell being left, entered with CDF c_in */
        /* rays in their sure-free zone wait in sk, by the ray length (metres) where the zone ends (shortened
           by 1e-12: t_out < sk.t implies t_out * sc < z_sure); the others are active, evaluated every cell */
        int64_t n_act = 0, n_sure = 0, s_head = 0;
        for (int64_t j = 0; j < m; ++j) {
            if (st[j].sure) {
                sk[n_sure].t = st[j].sc > 0.0 ? st[j].z_sure / st[j].sc * (1.0 - 1e-12) : DBL_MAX;
                sk[n_sure++].j = j;
            } else act[n_act++] = j;
        }
        if (n_sure > 1) qsort(sk, (size_t) n_sure, sizeof(SortKey), cmp_sort_key);
        for (;;) {
            if (t0 < t1) {
                if (t0 < t2) { lin += d0; t0 += dt0; } else { lin += d2; t2 += dt2; }
            } else if (t1 < t2) { lin += d1; t1 += dt1; } else { lin += d2; t2 += dt2; }
            int at_end = lin == lin_end;
            double dist = t0 < t1 ? t0 : t1;
            dist = dist < t2 ? dist : t2;
            int stop = at_end || dist > len;
            if (n_act == 0 && !stop && s_head < n_sure && t_out < sk[s_head].t) {
                /* every ray of the group still in its sure-free zone (most of a ray's length): the cell left
                   gets the whole miss that stands for them — the general step below would give the same */
                PUT_MISS(cell);
                t_in = t_out;
                t_out = dist;
                cell = lin;
                continue;
            }
            while (s_head < n_sure && (stop || t_out >= sk[s_head].t)) {   /* leaving its zone: exact from here */
                RayState *r = st + sk[s_head].j;
                r->sure = 0;
                r->c_in = cdf_at(t_in * r->sc, r->p, r->e, K, &r->k, &r->cum);   /* where the cell was entered */
                act[n_act++] = sk[s_head++].j;
            }
            /* the cell left now: free cell of the rays */
            float best = 0.0f;
            for (int64_t a = 0; a < n_act; ++a) {
                RayState *r = st + act[a];
                r->c_out = cdf_at(t_out * r->sc, r->p, r->e, K, &r->k, &r->cum);
                COMBINE(best, (float) ((r->c_out - r->c_in) * dhit + (r->mass - r->c_out + r->pb) * dmiss));
            }
            /* a whole miss stands for the waiting rays' updates (all <= thr <= -min_update: they pass the filter
               and snap to a miss; the stand-in is combined without the filter, as they would be) */
            if (s_head < n_sure) COMBINE_ANY(best, miss);
            PUT(cell, best);
            if (stop) {                  /* the end cell: from here to past the end point */
                if (end_ok) {
                    double t_end = dist > len ? dist : len;
                    if (!at_end) t_end = len > t_out ? len : t_out;
                    float best_end = 0.0f;
                    for (int64_t a = 0; a < n_act; ++a) {
                        RayState *r = st + act[a];
                        double c_end = cdf_at(t_end * r->sc, r->p, r->e, K, &r->k, &r->cum);
                        COMBINE(best_end, (float) ((c_end - r->c_out) * dhit + (r->mass - c_end + r->pb) * dmiss));
                    }
                    PUT(lin_end, best_end);
                }
                break;
            }
            int64_t kept = 0;
            for (int64_t a = 0; a < n_act; ++a) {
                RayState *r = st + act[a];
                if (r->mass - r->c_out + r->pb <= 0.0) continue;   /* no mass left from here on: the ray ends */
                r->c_in = r->c_out;
                act[kept++] = act[a];
            }
            n_act = kept;
            if (n_act == 0 && s_head == n_sure) break;
            t_in = t_out;
            t_out = dist;
            cell = lin;
        }
    }
    ret = off;
done:
    free(st);
    free(act);
    free(sk);
    return ret;
}

/* Merge accumulator b into a at b's n indices (mm_ray_weights' rule: the largest positive, else the most
   negative), zeroing b there; indices new to a are written to fresh (returns their count). */
int64_t mm_acc_merge(const int64_t *lin, int64_t n, float *a, float *b, int64_t *fresh)
{
    int64_t m = 0;
    for (int64_t i = 0; i < n; ++i) {
        const int64_t x = lin[i];
        const float o = a[x], v = b[x];
        b[x] = 0.0f;
        if (o == 0.0f) { a[x] = v; fresh[m++] = x; }
        else if (v > 0.0f ? (o < 0.0f || v > o) : (o < 0.0f && v < o)) a[x] = v;
    }
    return m;
}

/* distribution.quantise_updates on n updates dl at indices lin (quantum > 0: rounded to multiples of quantum
   in float64, half to even as np.round, except values equal to hit or miss; snap: negatives become miss where
   <= miss / 2, else 0), the zeros dropped and the rest split by sign, each part in input order: the negatives
   to out_lin / out_dl[0 .. *n_neg), the positives after them; returns the number written. */
int64_t mm_quantise_split(const int64_t *lin, const float *dl, int64_t n, float hit, float miss, double quantum,
                          int snap, int64_t *out_lin, float *out_dl, int64_t *n_neg)
{
    int64_t neg = 0, pos = n;            /* negatives forward from the front, positives backward from the end */
    for (int64_t i = 0; i < n; ++i) {
        float v = dl[i];
        if (quantum > 0.0 && v != hit && v != miss)
            v = (float) (nearbyint((double) v / quantum) * quantum);
        if (snap && v < 0.0f) v = v <= miss / 2.0f ? miss : 0.0f;
        if (v == 0.0f) continue;
        int64_t at = v < 0.0f ? neg++ : --pos;
        out_lin[at] = lin[i];
        out_dl[at] = v;
    }
    /* the positives were written back to front: reverse them into input order, right after the negatives */
    for (int64_t a = pos, b = n - 1; a < b; ++a, --b) {
        int64_t tl = out_lin[a]; out_lin[a] = out_lin[b]; out_lin[b] = tl;
        float tv = out_dl[a]; out_dl[a] = out_dl[b]; out_dl[b] = tv;
    }
    if (pos > neg) {
        memmove(out_lin + neg, out_lin + pos, sizeof(int64_t) * (size_t) (n - pos));
        memmove(out_dl + neg, out_dl + pos, sizeof(float) * (size_t) (n - pos));
    }
    *n_neg = neg;
    return neg + (n - pos);
}

/* dl[i] = acc[lin[i]] for n indices, zeroing acc there (the buffer is left zeroed for the next frame). */
void mm_acc_take(const int64_t *lin, int64_t n, float *acc, float *dl)
{
    for (int64_t i = 0; i < n; ++i) { dl[i] = acc[lin[i]]; acc[lin[i]] = 0.0f; }
}

/* coordToKey for n float64 points (OctoMap: (int) floor(resolution_factor * (double)(float) p) + tree_max_val):
   float32 copies to pts32, keys to keys (n x 3), their inclusive bounds to lo / hi; returns the number of
   points whose key is outside [0, 2 * tree_max_val) (their keys are then meaningless). */
int64_t mm_point_keys(const double *pts, int64_t n, double rf, int64_t tree_max_val, float *pts32,
                      int64_t *keys, int64_t *lo, int64_t *hi)
{
    int64_t bad = 0;
    for (int a = 0; a < 3; ++a) { lo[a] = INT64_MAX; hi[a] = INT64_MIN; }
    for (int64_t i = 0; i < 3 * n; i += 3) {
        for (int a = 0; a < 3; ++a) {
            float f = (float) pts[i + a];
            pts32[i + a] = f;
            double c = rf * (double) f;    /* floor(c) in [-tmv, tmv) <=> c in [-tmv, tmv) */
            if (!(c >= (double) -tree_max_val && c < (double) tree_max_val)) { ++bad; keys[i + a] = 0; continue; }
            int64_t t = (int64_t) c;         /* floor without the libm call: truncate, then one down if above */
            int64_t k = t - ((double) t > c) + tree_max_val;
            keys[i + a] = k;
            if (k < lo[a]) lo[a] = k;
            if (k > hi[a]) hi[a] = k;
        }
    }
    return bad;
}

/* computeDiscreteUpdate's deduplication through the box bitmap: for each of n keys, the first one in its cell
   sets mark[cell] = 2 and writes its row to rows and, with centres, its cell centre (float) to centres;
   returns the count (-2: a key outside the box). */
int64_t mm_unique_cells(const int64_t *keys, int64_t n, const int64_t *lo, const int64_t *strides, uint8_t *mark,
                        int64_t mark_size, double res, int64_t tree_max_val, int64_t *rows, float *centres)
{
    int64_t m = 0;
    for (int64_t i = 0; i < n; ++i) {
        const int64_t *k = keys + 3 * i;
        int64_t x = box_index(k, lo, strides);
        if (x < 0 || x >= mark_size) return -2;
        if (mark[x] == 2) continue;
        mark[x] = 2;
        rows[m] = i;
        if (centres)
            for (int a = 0; a < 3; ++a)
                centres[3 * m + a] = (float) (((double) (k[a] - tree_max_val) + 0.5) * res);
        ++m;
    }
    return m;
}

/* Exact floor division of 0 <= a < 2^50 by d > 0 through a double reciprocal (off by at most one, corrected):
   several times faster than the integer division. */
static inline int64_t div_fast(int64_t a, int64_t d, double inv)
{
    int64_t q = (int64_t) ((double) a * inv), r = a - q * d;
    if (r < 0) --q;
    else if (r >= d) ++q;
    return q;
}

/* Keys (n x 3) of linear box indices (KeyBox.keys). */
void mm_box_keys(const int64_t *lin, int64_t n, const int64_t *lo, const int64_t *strides, int64_t *keys)
{
    const int64_t s0 = strides[0], s1 = strides[1];
    const double i0 = 1.0 / (double) s0, i1 = 1.0 / (double) s1;
    for (int64_t i = 0; i < n; ++i) {
        int64_t a = div_fast(lin[i], s0, i0), r = lin[i] - a * s0;
        int64_t b = div_fast(r, s1, i1);
        keys[3 * i] = a + lo[0];
        keys[3 * i + 1] = b + lo[1];
        keys[3 * i + 2] = r - b * s1 + lo[2];
    }
}

/* The log-odds mirror (mono_map/mapping/integrate.py, LogOddsMirror): blocks of 8x8x8 cells, slot table[flat]
   (int32, -1 = none) over a dense box of blocks (low corner tlo, shape tsh); cell (x, y, z) of a block at
   pool[slot * 512 + (x & 7) * 64 + (y & 7) * 8 + (z & 7)]. */
static inline int64_t block_flat(const int64_t *k, const int64_t *tlo, const int64_t *tsh)
{
    int64_t b0 = (k[0] >> 3) - tlo[0], b1 = (k[1] >> 3) - tlo[1], b2 = (k[2] >> 3) - tlo[2];
    if (b0 < 0 || b0 >= tsh[0] || b1 < 0 || b1 >= tsh[1] || b2 < 0 || b2 >= tsh[2]) return -1;
    return (b0 * tsh[1] + b1) * tsh[2] + b2;
}

/* Give every block of the n keys a slot: missing blocks get slots n_blocks, n_blocks + 1, ... in order of first
   appearance, their flat table indices written to new_flat; returns how many (-2: a key outside the table). */
int64_t mm_mirror_alloc(const int64_t *keys, int64_t n, int32_t *table, const int64_t *tlo, const int64_t *tsh,
                        int64_t n_blocks, int64_t *new_flat)
{
    int64_t m = 0;
    for (int64_t i = 0; i < n; ++i) {
        int64_t f = block_flat(keys + 3 * i, tlo, tsh);
        if (f < 0) return -2;
        if (table[f] < 0) { table[f] = (int32_t) (n_blocks + m); new_flat[m++] = f; }
    }
    return m;
}

/* OctoMap's updateNode(key, log-odds update) for n distinct cells on the mirror (every block allocated): a cell
   already clamped in the update's direction is left alone (updateNode's early abort), otherwise
   new = clamp((known ? old : 0) + u) (float arithmetic), dirty[block slot] = 1. upd: per-key updates, or NULL for
   u_all. Rows whose occupied state (>= thres) flipped go to flip_rows (count in *n_flip). Returns the number of
   cells changed, -2 if a block is missing. */
int64_t mm_mirror_apply(const int64_t *keys, int64_t n, const float *upd, float u_all, const int32_t *table,
                        const int64_t *tlo, const int64_t *tsh, float *pool, uint8_t *dirty, float cmin,
                        float cmax, float thres, int64_t *flip_rows, int64_t *n_flip)
{
    int64_t changed = 0, nf = 0;
    for (int64_t i = 0; i < n; ++i) {
        const int64_t *k = keys + 3 * i;
        int64_t f = block_flat(k, tlo, tsh);
        if (f < 0 || table[f] < 0) return -2;
        int64_t x = (int64_t) table[f] * 512 + ((k[0] & 7) << 6) + ((k[1] & 7) << 3) + (k[2] & 7);
        float u = upd ? upd[i] : u_all;
        float old = pool[x];
        int known = !isnan(old);
        if (known && ((u >= 0.0f && old >= cmax) || (u <= 0.0f && old <= cmin))) continue;
        float v = (known ? old : 0.0f) + u;
        if (v < cmin) v = cmin;
        if (v > cmax) v = cmax;
        pool[x] = v;
        dirty[table[f]] = 1;
        ++changed;
        int was = known && old >= thres, is = v >= thres;
        if (was != is) flip_rows[nf++] = i;
    }
    *n_flip = nf;
    return changed;
}

/* OctoMap's .ot node stream (mono_map/mapping/octree.py: pre-order, per node float32 log-odds + child-mask
   byte; eight equal leaf children collapse into their parent, an inner node holds its children's maximum) of
   the mirror's known cells, straight from its 8x8x8 blocks: block b (pool + slot[b] * 512) at depth-13 code
   codes[b] (z, y, x bits interleaved), blocks sorted by code. With out == NULL the same walk only counts the
   nodes and leaves (the tree OctoMap would hold), and with a block cache (per block slot: dirty flag, kind,
   value, nodes, leaves) only the blocks marked dirty are walked, the others read from the cache. */
struct ot_ctx {
    uint8_t *out; int64_t pos, cap, leaves; int err; const float *pool; const int64_t *slot; const int64_t *codes;
    uint8_t *bdirty; int8_t *bkind; float *bval; int64_t *bnodes, *bleaves;
};

static inline void ot_put(struct ot_ctx *c, int64_t p, float v, uint8_t mask)
{
    if (!c->out) return;
    memcpy(c->out + 5 * p, &v, 4);
    c->out[5 * p + 4] = mask;
}

/* 0: no known cell below, 1: inner node, 2: leaf; *v: the node's value */
static int ot_child_sum(struct ot_ctx *c, int64_t p, const int *kind, const float *vals, float *v)
{
    uint8_t mask = 0;
    int nleaf = 0, any = 0;
    float vmax = 0.0f, vmin = 0.0f;
    for (int i = 0; i < 8; ++i) {
        if (!kind[i]) continue;
        mask |= (uint8_t) (1u << i);
        nleaf += kind[i] == 2;
        if (!any) { vmax = vmin = vals[i]; any = 1; }
        else { if (vals[i] > vmax) vmax = vals[i]; if (vals[i] < vmin) vmin = vals[i]; }
    }
    if (!mask) { c->pos = p; return 0; }
    *v = vmax;
    if (mask == 0xFF && nleaf == 8 && vmin == vmax) {   /* eight leaves become one */
        c->pos = p + 1; c->leaves -= 7; ot_put(c, p, vmax, 0); return 2;
    }
    ot_put(c, p, vmax, mask);
    return 1;
}

static int ot_cells(struct ot_ctx *c, const float *blk, int s, int x, int y, int z, float *v)
{
    if (s == 1) {
        float f = blk[(x << 6) | (y << 3) | z];
        if (isnan(f)) return 0;
        if (c->pos >= c->cap) { c->err = 1; return 0; }
        ot_put(c, c->pos++, f, 0);
        ++c->leaves;
        *v = f;
        return 2;
    }
    if (c->pos >= c->cap) { c->err = 1; return 0; }
    int64_t p = c->pos++;
    int h = s >> 1, kind[8];
    float vals[8];
    for (int i = 0; i < 8; ++i)
        kind[i] = ot_cells(c, blk, h, x + (i & 1) * h, y + ((i >> 1) & 1) * h, z + ((i >> 2) & 1) * h, vals + i);
    return ot_child_sum(c, p, kind, vals, v);
}

/* One block's subtree: walked, or read from the block cache when it has not changed since it was cached. */
static int ot_block(struct ot_ctx *c, int64_t b, float *v)
{
    int64_t s = c->slot[b];
    if (c->bkind && !c->bdirty[s]) {
        c->pos += c->bnodes[s];
        c->leaves += c->bleaves[s];
        *v = c->bval[s];
        return c->bkind[s];
    }
    int64_t p0 = c->pos, l0 = c->leaves;
    float w = 0.0f;
    int k = ot_cells(c, c->pool + s * 512, 8, 0, 0, 0, &w);
    *v = w;
    if (c->bkind) {
        c->bnodes[s] = c->pos - p0; c->bleaves[s] = c->leaves - l0;
        c->bkind[s] = (int8_t) k; c->bval[s] = w; c->bdirty[s] = 0;
    }
    return k;
}

static int ot_blocks(struct ot_ctx *c, int depth, int64_t a, int64_t b, float *v)
{
    if (depth == 13) return ot_block(c, a, v);
    if (c->pos >= c->cap) { c->err = 1; return 0; }
    int64_t p = c->pos++;
    int shift = 3 * (12 - depth), kind[8] = {0, 0, 0, 0, 0, 0, 0, 0};
    float vals[8];
    for (int64_t i = a; i < b;) {
        int ci = (int) ((c->codes[i] >> shift) & 7);
        int64_t j = i + 1;
        while (j < b && (int) ((c->codes[j] >> shift) & 7) == ci) ++j;
        kind[ci] = ot_blocks(c, depth + 1, i, j, vals + ci);
        i = j;
    }
    return ot_child_sum(c, p, kind, vals, v);
}

/* Writes the stream's nodes (5 bytes each) to out (cap nodes; out == NULL: count only); returns their number,
   -1 if cap is too small; *leaves: the leaf count. bdirty ... bleaves: the block cache, or all NULL. */
int64_t mm_ot_nodes(const float *pool, const int64_t *slot, const int64_t *codes, int64_t n_blocks, uint8_t *out,
                    int64_t cap, int64_t *leaves, uint8_t *bdirty, int8_t *bkind, float *bval, int64_t *bnodes,
                    int64_t *bleaves)
{
    struct ot_ctx c = {out, 0, out ? cap : INT64_MAX, 0, 0, pool, slot, codes, bdirty, bkind, bval, bnodes, bleaves};
    float v;
    *leaves = 0;
    if (n_blocks == 0) return 0;
    ot_blocks(&c, 0, 0, n_blocks, &v);
    *leaves = c.leaves;
    return c.err ? -1 : c.pos;
}

/* Reads OctoMap's .ot node stream (pre-order; per node its float log-odds, then a byte whose bit i says
   child i exists): every leaf's min-corner key (x, y, z), depth (0 = root) and log-odds. Returns the leaf
   count; -1 if more than cap leaves, -2 if the stream ends inside a node, -3 if it is deeper than 16. */
struct otp { const uint8_t *d; int64_t n, pos, cap, m; int64_t *keys; int8_t *depth; float *val; int err; };

static void otp_node(struct otp *c, int level, int64_t kx, int64_t ky, int64_t kz)
{
    if (c->err) return;
    if (c->pos + 5 > c->n) { c->err = -2; return; }
    float v;
    memcpy(&v, c->d + c->pos, 4);
    uint8_t mask = c->d[c->pos + 4];
    c->pos += 5;
    if (mask == 0) {
        if (c->m >= c->cap) { c->err = -1; return; }
        c->keys[3 * c->m] = kx; c->keys[3 * c->m + 1] = ky; c->keys[3 * c->m + 2] = kz;
        c->depth[c->m] = (int8_t) level; c->val[c->m] = v; c->m++;
        return;
    }
    if (level >= 16) { c->err = -3; return; }
    int64_t bit = (int64_t) 1 << (15 - level);
    for (int i = 0; i < 8; ++i)
        if (mask & (1 << i))
            otp_node(c, level + 1, kx | ((i & 1) ? bit : 0), ky | ((i & 2) ? bit : 0), kz | ((i & 4) ? bit : 0));
}

int64_t mm_ot_leaves(const uint8_t *data, int64_t n, int64_t cap, int64_t *keys, int8_t *depth, float *val)
{
    struct otp c = {data, n, 0, cap, 0, keys, depth, val, 0};
    if (n > 0) otp_node(&c, 0, 0, 0, 0);
    return c.err ? c.err : c.m;
}

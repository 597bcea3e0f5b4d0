/*
 * se3sync plant: model equations, RKMK4 integrator on SE(3) x R^6 (its step in rkmk4.h), validation.
 * No FMI types here (see fmi2.c).  Every function works on the ModelData it is given;
 * there is no global or static mutable data.
 */
#include "model.h"

#include <math.h>
#include <stdio.h>
#include <string.h>
/* The small vector helpers must be inlined into rkmk4_step so that the stage vectors
 * live in registers: this halves the cost per step at -O2. */
#if defined(__GNUC__) || defined(__clang__)
#define ALWAYS_INLINE inline __attribute__((always_inline))
#elif defined(_MSC_VER)
#define ALWAYS_INLINE __forceinline
#else
#define ALWAYS_INLINE inline
#endif

/* ------------------------------------------------------------------ small helpers */

#define PI_ 3.14159265358979323846

static int is_finite(double x) { return isfinite(x); }

/* unit quaternion (w, x, y, z) -> rotation matrix, row-major */
static void R_from_quat(const double q[4], double R[9])
{
    const double w = q[0], x = q[1], y = q[2], z = q[3];
    R[0] = 1.0 - 2.0 * (y * y + z * z);
    R[1] = 2.0 * (x * y - w * z);
    R[2] = 2.0 * (x * z + w * y);
    R[3] = 2.0 * (x * y + w * z);
    R[4] = 1.0 - 2.0 * (x * x + z * z);
    R[5] = 2.0 * (y * z - w * x);
    R[6] = 2.0 * (x * z - w * y);
    R[7] = 2.0 * (y * z + w * x);
    R[8] = 1.0 - 2.0 * (x * x + y * y);
}

void model_quat_from_R(const double R[9], double q[4])
{
    /* Shepperd (1978): pick the largest of 1+tr, 1+2R00-tr, ... to avoid cancellation */
    const double tr = R[0] + R[4] + R[8];
    double w, x, y, z, s;
    if (tr >= R[0] && tr >= R[4] && tr >= R[8]) {
        w = 0.5 * sqrt(1.0 + tr);
        s = 0.25 / w;
        x = (R[7] - R[5]) * s;
        y = (R[2] - R[6]) * s;
        z = (R[3] - R[1]) * s;
    } else if (R[0] >= R[4] && R[0] >= R[8]) {
        x = 0.5 * sqrt(1.0 + R[0] - R[4] - R[8]);
        s = 0.25 / x;
        w = (R[7] - R[5]) * s;
        y = (R[1] + R[3]) * s;
        z = (R[2] + R[6]) * s;
    } else if (R[4] >= R[8]) {
        y = 0.5 * sqrt(1.0 - R[0] + R[4] - R[8]);
        s = 0.25 / y;
        w = (R[2] - R[6]) * s;
        x = (R[1] + R[3]) * s;
        z = (R[5] + R[7]) * s;
    } else {
        z = 0.5 * sqrt(1.0 - R[0] - R[4] + R[8]);
        s = 0.25 / z;
        w = (R[3] - R[1]) * s;
        x = (R[2] + R[6]) * s;
        y = (R[5] + R[7]) * s;
    }
    if (w < 0.0) {
        w = -w; x = -x; y = -y; z = -z;
    }
    q[0] = w; q[1] = x; q[2] = y; q[3] = z;
}

/* ------------------------------------------------------------------ variables */

void model_update_quaternions(ModelData *d)
{
    if (d->q_valid) return;
    for (int b = 0; b < N_BODIES; b++) model_quat_from_R(d->body[b].out + OFF_R, d->body[b].out + OFF_Q);
    d->q_valid = 1;
}

void model_set_defaults(ModelData *d)
{
    memset(d, 0, sizeof *d);
    d->h_internal = 1e-4;
    for (int b = 0; b < N_BODIES; b++) {
        double *par = d->body[b].par;
        par[PAR_M] = 1.0;
        par[PAR_J + 0] = 1.0;
        par[PAR_J + 4] = 1.0;
        par[PAR_J + 8] = 1.0;
        par[PAR_Q0] = 1.0;
    }
    model_preview(d);
}

double *model_lookup(ModelData *d, unsigned int vr, int *kind)
{
    *kind = VAR_UNKNOWN;
    if (vr >= VR_GRAVITY && vr < VR_GRAVITY + 3) {
        *kind = VAR_PARAMETER;
        return &d->g[vr - VR_GRAVITY];
    }
    if (vr == VR_H_INTERNAL) {
        *kind = VAR_PARAMETER;
        return &d->h_internal;
    }
    switch (vr) {
    case VR_GROUND: *kind = VAR_PARAMETER; return &d->ground;
    case VR_GROUND_HEIGHT: *kind = VAR_PARAMETER; return &d->ground_height;
    case VR_DRAG_LINEAR: *kind = VAR_PARAMETER; return &d->drag_linear;
    case VR_DRAG_ANGULAR: *kind = VAR_PARAMETER; return &d->drag_angular;
    default: break;
    }
    if (vr < VR_BODY_BASE) return NULL;
    {
        const unsigned int k = vr - VR_BODY_BASE;
        const unsigned int b = k / VR_BODY_STRIDE, off = k % VR_BODY_STRIDE;
        if (b >= (unsigned int)N_BODIES) return NULL;
        if (off < N_OUT) {
            *kind = VAR_OUTPUT;
            return &d->body[b].out[off];
        }
        if (off >= OFF_U && off < OFF_U + N_U) {
            *kind = VAR_INPUT;
            return &d->body[b].u[off - OFF_U];
        }
        if (off >= OFF_PAR && off < OFF_PAR + N_PAR) {
            *kind = VAR_PARAMETER;
            return &d->body[b].par[off - OFF_PAR];
        }
    }
    return NULL;
}

double *model_lookup_run(ModelData *d, const unsigned int *vr, size_t nvr, int *kind, size_t *run,
                         unsigned int *offset)
{
    double *p = model_lookup(d, vr[0], kind);
    size_t r = 1, limit;
    unsigned int off = 0, end = 1;
    if (!p) {
        *run = 0;
        return NULL;
    }
    if (vr[0] >= VR_BODY_BASE) {
        off = (vr[0] - VR_BODY_BASE) % VR_BODY_STRIDE;
        end = *kind == VAR_OUTPUT ? N_OUT : *kind == VAR_INPUT ? OFF_U + N_U : OFF_PAR + N_PAR;
    } else if (vr[0] < VR_GRAVITY + 3) {
        off = vr[0] - VR_GRAVITY;
        end = 3;
    }
    limit = end - off < nvr ? end - off : nvr;
    while (r < limit && vr[r] == vr[0] + r) r++;
    *run = r;
    *offset = off;
    return p;
}

void model_variable_name(unsigned int vr, char *buf, size_t n)
{
    if (vr >= VR_GRAVITY && vr < VR_GRAVITY + 3) {
        snprintf(buf, n, "g[%u]", vr - VR_GRAVITY + 1);
        return;
    }
    if (vr == VR_H_INTERNAL) {
        snprintf(buf, n, "h_internal");
        return;
    }
    {
        static const char *const names[] = {"ground", "ground_height", "drag_linear", "drag_angular"};
        if (vr >= VR_GROUND && vr <= VR_DRAG_ANGULAR) {
            snprintf(buf, n, "%s", names[vr - VR_GROUND]);
            return;
        }
    }
    if (vr >= VR_BODY_BASE) {
        const unsigned int k = vr - VR_BODY_BASE;
        const unsigned int b = k / VR_BODY_STRIDE, off = k % VR_BODY_STRIDE;
        if (b < (unsigned int)N_BODIES) {
            const unsigned int i = b + 1;
            if (off < OFF_R) { snprintf(buf, n, "body[%u].p[%u]", i, off - OFF_P + 1); return; }
            if (off < OFF_XI) {
                snprintf(buf, n, "body[%u].R[%u,%u]", i, (off - OFF_R) / 3 + 1, (off - OFF_R) % 3 + 1);
                return;
            }
            if (off < OFF_Q) { snprintf(buf, n, "body[%u].xi[%u]", i, off - OFF_XI + 1); return; }
            if (off < OFF_CONTACT) { snprintf(buf, n, "body[%u].q[%u]", i, off - OFF_Q + 1); return; }
            if (off == OFF_CONTACT) { snprintf(buf, n, "body[%u].contact", i); return; }
            if (off >= OFF_U && off < OFF_U + N_U) { snprintf(buf, n, "body[%u].u[%u]", i, off - OFF_U + 1); return; }
            if (off >= OFF_PAR && off < OFF_PAR + N_PAR) {
                const unsigned int j = off - OFF_PAR;
                if (j == PAR_M) { snprintf(buf, n, "body[%u].m", i); return; }
                if (j < PAR_P0) {
                    snprintf(buf, n, "body[%u].J[%u,%u]", i, (j - PAR_J) / 3 + 1, (j - PAR_J) % 3 + 1);
                    return;
                }
                if (j < PAR_Q0) { snprintf(buf, n, "body[%u].p0[%u]", i, j - PAR_P0 + 1); return; }
                if (j < PAR_XI0) { snprintf(buf, n, "body[%u].q0[%u]", i, j - PAR_Q0 + 1); return; }
                snprintf(buf, n, "body[%u].xi0[%u]", i, j - PAR_XI0 + 1);
                return;
            }
        }
    }
    snprintf(buf, n, "<unknown value reference %u>", vr);
}

/* ------------------------------------------------------------------ validation */

/* eigenvalues of a symmetric 3x3 matrix, ascending (closed form, Smith 1961) */
static void sym3_eigenvalues(const double A[9], double ev[3])
{
    const double p1 = A[1] * A[1] + A[2] * A[2] + A[5] * A[5];
    const double q = (A[0] + A[4] + A[8]) / 3.0;
    const double a0 = A[0] - q, a1 = A[4] - q, a2 = A[8] - q;
    const double p2 = a0 * a0 + a1 * a1 + a2 * a2 + 2.0 * p1;
    if (p2 <= 0.0) {
        ev[0] = ev[1] = ev[2] = q;
        return;
    }
    {
        const double p = sqrt(p2 / 6.0);
        const double b0 = a0 / p, b1 = a1 / p, b2 = a2 / p;
        const double b01 = A[1] / p, b02 = A[2] / p, b12 = A[5] / p;
        double r = 0.5 * (b0 * (b1 * b2 - b12 * b12) - b01 * (b01 * b2 - b12 * b02)
                          + b02 * (b01 * b12 - b1 * b02));
        double phi, e1, e3;
        if (r <= -1.0) phi = PI_ / 3.0;
        else if (r >= 1.0) phi = 0.0;
        else phi = acos(r) / 3.0;
        e1 = q + 2.0 * p * cos(phi);                 /* largest */
        e3 = q + 2.0 * p * cos(phi + 2.0 * PI_ / 3.0); /* smallest */
        ev[0] = e3;
        ev[1] = 3.0 * q - e1 - e3;
        ev[2] = e1;
    }
}

/* inverse of a symmetric 3x3 matrix by cofactors, computed on A / 2^e with 2^e ~ max|A| so that
 * the cofactors and the determinant (products of 2 and 3 entries) neither underflow nor overflow
 * for any accepted scale; scaling by a power of two is exact, so the result is bit for bit the
 * unscaled formula's wherever that one does not underflow/overflow */
static void sym3_inverse(const double A0[9], double Ai[9])
{
    double A[9], s = 0.0;
    int e = 0;
    for (int k = 0; k < 9; k++) s = fmax(s, fabs(A0[k]));
    (void)frexp(s, &e);
    for (int k = 0; k < 9; k++) A[k] = ldexp(A0[k], -e);
    {
        const double c00 = A[4] * A[8] - A[5] * A[7];
        const double c01 = A[5] * A[6] - A[3] * A[8];
        const double c02 = A[3] * A[7] - A[4] * A[6];
        const double det = A[0] * c00 + A[1] * c01 + A[2] * c02;
        const double id = 1.0 / det;
        Ai[0] = c00 * id;
        Ai[1] = (A[2] * A[7] - A[1] * A[8]) * id;
        Ai[2] = (A[1] * A[5] - A[2] * A[4]) * id;
        Ai[3] = c01 * id;
        Ai[4] = (A[0] * A[8] - A[2] * A[6]) * id;
        Ai[5] = (A[2] * A[3] - A[0] * A[5]) * id;
        Ai[6] = c02 * id;
        Ai[7] = (A[1] * A[6] - A[0] * A[7]) * id;
        Ai[8] = (A[0] * A[4] - A[1] * A[3]) * id;
    }
    for (int k = 0; k < 9; k++) Ai[k] = ldexp(Ai[k], -e);
}

#define LOGF(status, cat, ...)                                    \
    do {                                                          \
        if (log) {                                                \
            char msg_[512];                                       \
            snprintf(msg_, sizeof msg_, __VA_ARGS__);             \
            log(env, status, cat, msg_);                          \
        }                                                         \
    } while (0)

#define Q0_TOL        1e-3   /* | |q0| - 1 | above this: refused */
#define Q0_SILENT     1e-12  /* below this: normalised without a message */
#define J_SYM_TOL     1e-9   /* relative asymmetry allowed in J */
#define J_TRI_TOL     1e-9   /* relative slack in the triangle inequality */
#define J_PD_TOL      1e-14  /* smallest eigenvalue must exceed this times the largest */
#define GROUND_TOL    1e-9   /* m (relative to 1 + |ground_height|): "on the ground" at the start */
#define DRAG_STEP_MAX 2.5    /* h_internal / T of the fastest drag time constant */

static int validate_body(const ModelData *d, int b, ModelLogger log, void *env, double Jsym[9],
                         double q0n[4], int *normalised)
{
    const double *par = d->body[b].par;
    const int i = b + 1;
    char name[64];
    int ok = 1;
    *normalised = 0;
    for (int j = 0; j < N_PAR; j++) {
        if (!is_finite(par[j])) {
            model_variable_name(VR_BODY_BASE + VR_BODY_STRIDE * (unsigned)b + OFF_PAR + (unsigned)j, name,
                                sizeof name);
            LOGF(MODEL_ERROR, "logStatusError", "%s = %g is not finite", name, par[j]);
            ok = 0;
        }
    }
    if (!ok) return 0;
    if (!(par[PAR_M] > 0.0)) {
        LOGF(MODEL_ERROR, "logStatusError", "body[%d].m = %g must be > 0", i, par[PAR_M]);
        ok = 0;
    } else if (!(par[PAR_M] >= MAG_MIN && par[PAR_M] <= MAG_MAX)) {
        LOGF(MODEL_ERROR, "logStatusError", "body[%d].m = %g is outside the accepted range [%g, %g]", i, par[PAR_M],
             MAG_MIN, MAG_MAX);
        ok = 0;
    }
    {
        /* shape tests on Jn = J / 2^e with 2^e ~ max|J| (exact scaling): they do not depend on the
         * scale of J, and nothing in them can underflow or overflow */
        const double *J = par + PAR_J;
        double scale = 0.0, asym = 0.0, Jn[9], Jns[9], ev[3], lo, hi;
        int e = 0;
        for (int k = 0; k < 9; k++) scale = fmax(scale, fabs(J[k]));
        if (scale == 0.0) {
            LOGF(MODEL_ERROR, "logStatusError", "body[%d].J is zero (not positive definite)", i);
            return 0;
        }
        (void)frexp(scale, &e);
        for (int k = 0; k < 9; k++) Jn[k] = ldexp(J[k], -e);
        for (int r = 0; r < 3; r++)
            for (int c = 0; c < 3; c++) asym = fmax(asym, fabs(Jn[3 * r + c] - Jn[3 * c + r]));
        if (asym > J_SYM_TOL) {
            LOGF(MODEL_ERROR, "logStatusError",
                 "body[%d].J is not symmetric (max |J[r,c]-J[c,r]| = %.3g > %g * max|J|)", i, ldexp(asym, e),
                 J_SYM_TOL);
            return 0;
        }
        for (int r = 0; r < 3; r++)
            for (int c = 0; c < 3; c++) {
                Jns[3 * r + c] = 0.5 * (Jn[3 * r + c] + Jn[3 * c + r]);
                Jsym[3 * r + c] = 0.5 * J[3 * r + c] + 0.5 * J[3 * c + r]; /* no overflow near DBL_MAX */
            }
        sym3_eigenvalues(Jns, ev);
        lo = ldexp(ev[0], e); /* principal moments of J (for messages and the range check) */
        hi = ldexp(ev[2], e);
        if (!(ev[0] > J_PD_TOL * fabs(ev[2])) || !(ev[2] > 0.0)) {
            LOGF(MODEL_ERROR, "logStatusError", "body[%d].J is not positive definite (eigenvalues %.6g, %.6g, %.6g)",
                 i, lo, ldexp(ev[1], e), hi);
            ok = 0;
        } else if (ev[2] > ev[0] + ev[1] + J_TRI_TOL * (ev[0] + ev[1] + ev[2])) {
            /* ev ascending: only the largest can break the triangle inequality */
            LOGF(MODEL_ERROR, "logStatusError",
                 "body[%d].J: violates the triangle inequality (J1 + J2 >= J3): principal moments %.6g, %.6g, %.6g",
                 i, lo, ldexp(ev[1], e), hi);
            ok = 0;
        } else if (!(lo >= MAG_MIN && hi <= MAG_MAX)) {
            LOGF(MODEL_ERROR, "logStatusError",
                 "body[%d].J: principal moments %.3g..%.3g outside the accepted range [%g, %g]", i, lo, hi, MAG_MIN,
                 MAG_MAX);
            ok = 0;
        }
    }
    {
        const double *q = par + PAR_Q0;
        const double nq = sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]);
        if (!(nq > 0.0) || fabs(nq - 1.0) > Q0_TOL) {
            LOGF(MODEL_ERROR, "logStatusError",
                 "body[%d].q0 = (%g, %g, %g, %g) has norm %g: not a unit quaternion (tolerance %g)", i, q[0], q[1],
                 q[2], q[3], nq, Q0_TOL);
            ok = 0;
        } else {
            for (int k = 0; k < 4; k++) q0n[k] = q[k] / nq;
            if (fabs(nq - 1.0) > Q0_SILENT) *normalised = 1;
        }
    }
    return ok;
}

/* ------------------------------------------------------------------ optional terms: ground and drag */

/* the upward unit vector -g/|g| (only meaningful with g != 0) */
static void up_vector(const ModelData *d, double e[3])
{
    const double gn = sqrt(d->g[0] * d->g[0] + d->g[1] * d->g[1] + d->g[2] * d->g[2]);
    for (int k = 0; k < 3; k++) e[k] = gn > 0.0 ? -d->g[k] / gn : 0.0;
}

/* height of the centre of mass above the ground plane */
static double height_above_ground(const ModelData *d, const double e[3], const double p[3])
{
    return e[0] * p[0] + e[1] * p[1] + e[2] * p[2] - d->ground_height;
}

/* a body starts resting on the ground when it is on the plane (within GROUND_TOL) and at rest */
static int starts_in_contact(const ModelData *d, const Body *B)
{
    double e[3];
    if (d->ground != 1.0) return 0;
    up_vector(d, e);
    if (height_above_ground(d, e, B->par + PAR_P0) > GROUND_TOL * (1.0 + fabs(d->ground_height))) return 0;
    for (int k = 0; k < 6; k++)
        if (B->par[PAR_XI0 + k] != 0.0) return 0;
    return 1;
}

/* the global terms: ground in {0, 1} (1 needs g != 0), drag coefficients >= 0 */
static int validate_terms(const ModelData *d, ModelLogger log, void *env)
{
    int ok = 1;
    if (!is_finite(d->ground) || (d->ground != 0.0 && d->ground != 1.0)) {
        LOGF(MODEL_ERROR, "logStatusError", "ground = %g must be 0 (no ground) or 1 (a ground plane)", d->ground);
        ok = 0;
    } else if (d->ground == 1.0 && d->g[0] == 0.0 && d->g[1] == 0.0 && d->g[2] == 0.0) {
        LOGF(MODEL_ERROR, "logStatusError", "ground = 1 needs a nonzero gravity g (it defines which way is up)");
        ok = 0;
    }
    if (!is_finite(d->ground_height)) {
        LOGF(MODEL_ERROR, "logStatusError", "ground_height = %g is not finite", d->ground_height);
        ok = 0;
    }
    if (!is_finite(d->drag_linear) || !(d->drag_linear >= 0.0)) {
        LOGF(MODEL_ERROR, "logStatusError", "drag_linear = %g must be finite and >= 0", d->drag_linear);
        ok = 0;
    }
    if (!is_finite(d->drag_angular) || !(d->drag_angular >= 0.0)) {
        LOGF(MODEL_ERROR, "logStatusError", "drag_angular = %g must be finite and >= 0", d->drag_angular);
        ok = 0;
    }
    return ok;
}

/* per body, with J symmetrised: the start is not below the ground, and the drag's time constants are
 * resolved by the internal step (RK4 is stable on x' = -x/T for h/T < 2.78; DRAG_STEP_MAX keeps a margin) */
static int validate_body_terms(const ModelData *d, int b, const double Jsym[9], ModelLogger log, void *env)
{
    const Body *B = &d->body[b];
    int ok = 1;
    if (d->ground == 1.0) {
        double e[3], hgt;
        up_vector(d, e);
        hgt = height_above_ground(d, e, B->par + PAR_P0);
        if (hgt < -GROUND_TOL * (1.0 + fabs(d->ground_height))) {
            LOGF(MODEL_ERROR, "logStatusError", "body[%d].p0 is %g m below the ground (ground_height = %g)", b + 1,
                 -hgt, d->ground_height);
            ok = 0;
        }
    }
    if (d->drag_linear > 0.0 && d->drag_linear / B->par[PAR_M] * d->h_internal > DRAG_STEP_MAX) {
        LOGF(MODEL_ERROR, "logStatusError",
             "drag_linear = %g with body[%d].m = %g gives a time constant %g s, too short for h_internal = %g "
             "(h_internal / T must be <= %g)", d->drag_linear, b + 1, B->par[PAR_M],
             B->par[PAR_M] / d->drag_linear, d->h_internal, DRAG_STEP_MAX);
        ok = 0;
    }
    if (d->drag_angular > 0.0) {
        double ev[3];
        sym3_eigenvalues(Jsym, ev);
        if (d->drag_angular / ev[0] * d->h_internal > DRAG_STEP_MAX) {
            LOGF(MODEL_ERROR, "logStatusError",
                 "drag_angular = %g with body[%d].J (smallest principal moment %g) gives a time constant %g s, too "
                 "short for h_internal = %g (h_internal / T must be <= %g)", d->drag_angular, b + 1, ev[0],
                 ev[0] / d->drag_angular, d->h_internal, DRAG_STEP_MAX);
            ok = 0;
        }
    }
    return ok;
}

static void set_initial_state(Body *B, const double q0n[4])
{
    const double *par = B->par;
    double *out = B->out;
    memcpy(out + OFF_P, par + PAR_P0, 3 * sizeof(double));
    R_from_quat(q0n, out + OFF_R);
    memcpy(out + OFF_XI, par + PAR_XI0, 6 * sizeof(double));
    model_quat_from_R(out + OFF_R, out + OFF_Q);
}

int model_initialize(ModelData *d, ModelLogger log, void *env)
{
    int ok = 1, warn = 0;
    for (int k = 0; k < 3; k++) {
        if (!is_finite(d->g[k])) {
            LOGF(MODEL_ERROR, "logStatusError", "g[%d] = %g is not finite", k + 1, d->g[k]);
            ok = 0;
        }
    }
    if (!is_finite(d->h_internal) || !(d->h_internal >= H_INTERNAL_MIN)) {
        LOGF(MODEL_ERROR, "logStatusError", "h_internal = %g must be finite and >= %g", d->h_internal,
             H_INTERNAL_MIN);
        ok = 0;
    }
    const int terms_ok = validate_terms(d, log, env) && ok;
    if (!terms_ok) ok = 0;
    for (int b = 0; b < N_BODIES; b++) {
        double Jsym[9], q0n[4];
        int normalised;
        if (!validate_body(d, b, log, env, Jsym, q0n, &normalised)) ok = 0;
        else if (terms_ok && !validate_body_terms(d, b, Jsym, log, env)) ok = 0;
    }
    if (!ok) return MODEL_ERROR;
    for (int b = 0; b < N_BODIES; b++) {
        Body *B = &d->body[b];
        double Jsym[9], q0n[4];
        int normalised;
        validate_body(d, b, NULL, NULL, Jsym, q0n, &normalised);
        if (normalised) {
            const double *q = B->par + PAR_Q0;
            LOGF(MODEL_WARNING, "logStatusWarning",
                 "body[%d].q0 = (%.17g, %.17g, %.17g, %.17g) was normalised to unit length", b + 1, q[0], q[1], q[2],
                 q[3]);
            warn = 1;
        }
        memcpy(B->J, Jsym, sizeof Jsym);
        B->minv = 1.0 / B->par[PAR_M];
        sym3_inverse(Jsym, B->Jinv);
        set_initial_state(B, q0n);
        B->out[OFF_CONTACT] = starts_in_contact(d, B) ? 1.0 : 0.0;
    }
    d->q_valid = 1;
    return warn ? MODEL_WARNING : MODEL_OK;
}

void model_preview(ModelData *d)
{
    for (int b = 0; b < N_BODIES; b++) {
        Body *B = &d->body[b];
        const double *q = B->par + PAR_Q0;
        double nq = sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]);
        double q0n[4] = {1.0, 0.0, 0.0, 0.0};
        if (nq > 0.0 && is_finite(nq))
            for (int k = 0; k < 4; k++) q0n[k] = q[k] / nq;
        set_initial_state(B, q0n);
        B->out[OFF_CONTACT] = starts_in_contact(d, B) ? 1.0 : 0.0;
    }
    d->q_valid = 1;
}

/* ------------------------------------------------------------------ integrator */

/*
 * Coefficients of exp on so(3)/se(3) for theta^2 = |phi|^2:
 *   A = sin(t)/t,  B = (1 - cos t)/t^2,  C = (t - sin t)/t^3
 * with Taylor series (through t^6, truncation < 1e-22 relative) for t < 1e-2, where the
 * closed forms lose digits.
 */
/* the series, for a double or a vector of doubles (multiplications by constant reciprocals:
 * no divisions in the hot path) */
#define EXP_SERIES(T, th2, A, B, C)                                                                      \
    do {                                                                                              \
        const T c_ = 1.0 - (th2) * (1.0 / 20.0) * (1.0 - (th2) * (1.0 / 42.0) * (1.0 - (th2) * (1.0 / 72.0))); \
        *(A) = 1.0 - (th2) * (1.0 / 6.0) * c_;                                                         \
        *(B) = 0.5 * (1.0 - (th2) * (1.0 / 12.0) * (1.0 - (th2) * (1.0 / 30.0) * (1.0 - (th2) * (1.0 / 56.0)))); \
        *(C) = c_ * (1.0 / 6.0);                                                                       \
    } while (0)

static ALWAYS_INLINE void exp_coeffs(double th2, double *A, double *B, double *C)
{
    if (th2 < 1e-4) {
        EXP_SERIES(double, th2, A, B, C);
    } else {
        const double th = sqrt(th2), s = sin(th), hs = sin(0.5 * th);
        *A = s / th;
        *B = 2.0 * hs * hs / th2;
        *C = (th - s) / (th2 * th);
    }
}

/* one body at a time */
#define REAL double
#define SFX(name) name##_1
#define BODYT Body
#define EXPC exp_coeffs
#include "rkmk4.h"
#undef REAL
#undef SFX
#undef BODYT
#undef EXPC

#if (defined(__GNUC__) || defined(__clang__)) && !defined(SE3SYNC_NO_PAIRS)
#define SE3SYNC_PAIRS 1
/* two bodies at a time, one per lane (SSE2 on x86-64, NEON on arm64) */
typedef double v2d __attribute__((vector_size(16)));
typedef struct {
    v2d J[9], Jinv[9], minv, u[6];
} BodyPair;

/* exp_coeffs lane by lane: the series in vector arithmetic when both lanes take it, else each
 * lane through the scalar function (the same bits either way) */
static ALWAYS_INLINE void exp_coeffs_2(v2d th2, v2d *A, v2d *B, v2d *C)
{
    if (th2[0] < 1e-4 && th2[1] < 1e-4) {
        EXP_SERIES(v2d, th2, A, B, C);
    } else {
        double a0, b0, c0, a1, b1, c1;
        exp_coeffs(th2[0], &a0, &b0, &c0);
        exp_coeffs(th2[1], &a1, &b1, &c1);
        *A = (v2d){a0, a1};
        *B = (v2d){b0, b1};
        *C = (v2d){c0, c1};
    }
}

#define REAL v2d
#define SFX(name) name##_2
#define BODYT BodyPair
#define EXPC exp_coeffs_2
#include "rkmk4.h"
#undef REAL
#undef SFX
#undef BODYT
#undef EXPC

/* n RKMK4 steps of length hs of bodies a and b together */
static void step_pair(Body *a, Body *b, const double *gw, double hs, long long n)
{
    BodyPair P;
    v2d p[3], R[9], xi[6], g[3];
    for (int k = 0; k < 9; k++) {
        P.J[k] = (v2d){a->J[k], b->J[k]};
        P.Jinv[k] = (v2d){a->Jinv[k], b->Jinv[k]};
        R[k] = (v2d){a->out[OFF_R + k], b->out[OFF_R + k]};
    }
    for (int k = 0; k < 6; k++) {
        P.u[k] = (v2d){a->u[k], b->u[k]};
        xi[k] = (v2d){a->out[OFF_XI + k], b->out[OFF_XI + k]};
    }
    for (int k = 0; k < 3; k++) {
        p[k] = (v2d){a->out[OFF_P + k], b->out[OFF_P + k]};
        g[k] = gw ? (v2d){gw[k], gw[k]} : (v2d){0.0, 0.0};
    }
    P.minv = (v2d){a->minv, b->minv};
    for (long long s = 0; s < n; s++) rkmk4_step_2(&P, p, R, xi, gw ? g : NULL, hs);
    for (int k = 0; k < 9; k++) {
        a->out[OFF_R + k] = R[k][0];
        b->out[OFF_R + k] = R[k][1];
    }
    for (int k = 0; k < 6; k++) {
        a->out[OFF_XI + k] = xi[k][0];
        b->out[OFF_XI + k] = xi[k][1];
    }
    for (int k = 0; k < 3; k++) {
        a->out[OFF_P + k] = p[k][0];
        b->out[OFF_P + k] = p[k][1];
    }
}
#endif

/* one body at a time with the optional terms (drag in the acceleration; the ground between substeps) */
typedef struct {
    double J[9], Jinv[9], minv, u[6], cv, cw;
} BodyTerms;

#define REAL double
#define SFX(name) name##_x
#define BODYT BodyTerms
#define EXPC exp_coeffs
#define RKMK4_DRAG 1
#include "rkmk4.h"
#undef RKMK4_DRAG
#undef REAL
#undef SFX
#undef BODYT
#undef EXPC

/*
 * n substeps of length hs of body B with drag and/or the ground (see docs/reference/plant-fmu.md, "Ground and drag"):
 * - resting (contact = 1): the support balances gravity, thrust and torque (sticking contact: no
 *   sliding, no rotation) while the net force along up, e . R f - m |g|, is <= 0; nothing moves;
 * - otherwise an RKMK4 substep; if it ends below the plane, the body is put back on the plane
 *   along e and stopped (perfectly inelastic touchdown, no bounce) and rests from then on.
 * The check is on every substep's end point and the ground is a half-space, so no step size lets
 * the body pass through it.
 */
static void step_body_terms(const ModelData *d, Body *B, const double *gw, double hs, long long n)
{
    BodyTerms T;
    double *p = B->out + OFF_P, *R = B->out + OFF_R, *xi = B->out + OFF_XI;
    double e[3] = {0.0, 0.0, 0.0}, mg = 0.0;
    const int ground = d->ground == 1.0;
    memcpy(T.J, B->J, sizeof T.J);
    memcpy(T.Jinv, B->Jinv, sizeof T.Jinv);
    memcpy(T.u, B->u, sizeof T.u);
    T.minv = B->minv;
    T.cv = d->drag_linear;
    T.cw = d->drag_angular;
    if (ground) {
        up_vector(d, e);
        mg = B->par[PAR_M] * sqrt(d->g[0] * d->g[0] + d->g[1] * d->g[1] + d->g[2] * d->g[2]);
    }
    for (long long s = 0; s < n; s++) {
        if (B->out[OFF_CONTACT] != 0.0) {
            const double *f = B->u + 3;
            double fup = 0.0;
            for (int r = 0; r < 3; r++) fup += e[r] * (R[3 * r] * f[0] + R[3 * r + 1] * f[1] + R[3 * r + 2] * f[2]);
            if (!(fup > mg)) continue; /* held by the ground */
            B->out[OFF_CONTACT] = 0.0; /* lift-off */
        }
        rkmk4_step_x(&T, p, R, xi, gw, hs);
        if (ground) {
            const double hgt = height_above_ground(d, e, p);
            if (hgt < 0.0) { /* touchdown during this substep */
                for (int k = 0; k < 3; k++) p[k] -= hgt * e[k];
                for (int k = 0; k < 6; k++) xi[k] = 0.0;
                B->out[OFF_CONTACT] = 1.0;
            }
        }
    }
}

int model_check_step(const ModelData *d, double h, ModelLogger log, void *env)
{
    const double ratio = h / d->h_internal;
    const long long max_n = MAX_BODY_SUBSTEPS / N_BODIES;
    /* ceil(ratio - 1e-9) <= max_n; also refuses ratio = inf / NaN */
    if (!(ratio - 1e-9 <= (double)max_n)) {
        LOGF(MODEL_ERROR, "logStatusError",
             "communication step %g needs %.3g internal steps of h_internal = %g for each of %d bodies: over the "
             "limit of %lld body-steps per call (%lld per body); use a shorter step or a larger h_internal",
             h, ceil(ratio - 1e-9), d->h_internal, N_BODIES, MAX_BODY_SUBSTEPS, max_n);
        return MODEL_ERROR;
    }
    return MODEL_OK;
}

int model_do_step(ModelData *d, double h, ModelLogger log, void *env)
{
    const double ratio = h / d->h_internal;
    double n_d, hs;
    long long n;
    int ok = 1;
    const double *gw = (d->g[0] != 0.0 || d->g[1] != 0.0 || d->g[2] != 0.0) ? d->g : NULL;
    if (model_check_step(d, h, log, env) != MODEL_OK) return MODEL_ERROR;
    n_d = ceil(ratio - 1e-9);
    n = n_d < 1.0 ? 1 : (long long)n_d;
    hs = h / (double)n;
    int b = 0;
    if (d->ground != 0.0 || d->drag_linear != 0.0 || d->drag_angular != 0.0) {
        /* the optional terms: one body at a time through step_body_terms (off, nothing below changes) */
        for (; b < N_BODIES; b++) step_body_terms(d, &d->body[b], gw, hs, n);
    }
#ifdef SE3SYNC_PAIRS
    for (; b + 1 < N_BODIES; b += 2) step_pair(&d->body[b], &d->body[b + 1], gw, hs, n);
#endif
    for (; b < N_BODIES; b++) {
        Body *B = &d->body[b];
        for (long long s = 0; s < n; s++) rkmk4_step_1(B, B->out + OFF_P, B->out + OFF_R, B->out + OFF_XI, gw, hs);
    }
    for (b = 0; b < N_BODIES; b++) {
        const Body *B = &d->body[b];
        for (int k = 0; k < OFF_Q; k++) {
            if (!is_finite(B->out[k])) {
                ok = 0;
                LOGF(MODEL_ERROR, "logStatusError", "body[%d]: state is no longer finite at t = %g", b + 1,
                     d->time + h);
                break;
            }
        }
    }
    d->q_valid = 0; /* quaternions are computed on demand (model_update_quaternions) */
    if (!ok) return MODEL_ERROR;
    d->time += h;
    return MODEL_OK;
}

/* ------------------------------------------------------------------ restored states */

static int all_finite(const double *x, int n)
{
    for (int k = 0; k < n; k++)
        if (!is_finite(x[k])) return 0;
    return 1;
}

int model_validate_state(const ModelData *d, int initialized, int may_be_non_finite, ModelLogger log, void *env)
{
    if (!all_finite(d->g, 3) || !is_finite(d->time)) {
        LOGF(MODEL_ERROR, "logStatusError", "g or time is not finite");
        return MODEL_ERROR;
    }
    if (!is_finite(d->h_internal) || (initialized && !(d->h_internal >= H_INTERNAL_MIN))) {
        LOGF(MODEL_ERROR, "logStatusError", "h_internal = %g must be finite and >= %g", d->h_internal,
             H_INTERNAL_MIN);
        return MODEL_ERROR;
    }
    if (d->q_valid != 0 && d->q_valid != 1) {
        LOGF(MODEL_ERROR, "logStatusError", "q_valid = %d is not 0 or 1", d->q_valid);
        return MODEL_ERROR;
    }
    if (!is_finite(d->ground) || !is_finite(d->ground_height) || !is_finite(d->drag_linear)
        || !is_finite(d->drag_angular)) {
        LOGF(MODEL_ERROR, "logStatusError", "ground, ground_height, drag_linear or drag_angular is not finite");
        return MODEL_ERROR;
    }
    if (initialized && !validate_terms(d, log, env)) return MODEL_ERROR;
    for (int b = 0; b < N_BODIES; b++) {
        const Body *B = &d->body[b];
        const int i = b + 1;
        if (!all_finite(B->u, N_U) || !all_finite(B->par, N_PAR) || !all_finite(B->J, 9)
            || !all_finite(B->Jinv, 9) || !is_finite(B->minv)) {
            LOGF(MODEL_ERROR, "logStatusError", "body[%d]: an input or a parameter is not finite", i);
            return MODEL_ERROR;
        }
        if (!initialized) continue; /* parameters are checked at exitInitializationMode */
        {
            double Jsym[9], Jinv[9], q0n[4], minv;
            int normalised;
            if (!validate_body(d, b, log, env, Jsym, q0n, &normalised)) return MODEL_ERROR;
            if (!validate_body_terms(d, b, Jsym, log, env)) return MODEL_ERROR;
            if (B->out[OFF_CONTACT] != 0.0 && B->out[OFF_CONTACT] != 1.0) {
                LOGF(MODEL_ERROR, "logStatusError", "body[%d].contact = %g is not 0 or 1", i, B->out[OFF_CONTACT]);
                return MODEL_ERROR;
            }
            sym3_inverse(Jsym, Jinv);
            minv = 1.0 / B->par[PAR_M];
            if (memcmp(Jsym, B->J, sizeof Jsym) != 0 || memcmp(Jinv, B->Jinv, sizeof Jinv) != 0
                || memcmp(&minv, &B->minv, sizeof minv) != 0) {
                LOGF(MODEL_ERROR, "logStatusError", "body[%d]: stored J, J^-1 or 1/m does not match body[%d].J, .m", i,
                     i);
                return MODEL_ERROR;
            }
        }
        if (may_be_non_finite) continue;
        if (!all_finite(B->out, N_OUT)) {
            LOGF(MODEL_ERROR, "logStatusError", "body[%d]: state is not finite", i);
            return MODEL_ERROR;
        }
        {
            const double *R = B->out + OFF_R;
            double err = 0.0, det;
            for (int r = 0; r < 3; r++)
                for (int c = 0; c < 3; c++) {
                    const double rtr = R[r] * R[c] + R[3 + r] * R[3 + c] + R[6 + r] * R[6 + c];
                    err = fmax(err, fabs(rtr - (r == c ? 1.0 : 0.0)));
                }
            det = R[0] * (R[4] * R[8] - R[5] * R[7]) - R[1] * (R[3] * R[8] - R[5] * R[6])
                  + R[2] * (R[3] * R[7] - R[4] * R[6]);
            if (!(err <= R_ORTHO_TOL) || !(det > 0.0)) {
                LOGF(MODEL_ERROR, "logStatusError",
                     "body[%d].R is not a rotation (max |R^T R - I| = %.3g, tolerance %g; det %.6g)", i, err,
                     R_ORTHO_TOL, det);
                return MODEL_ERROR;
            }
        }
    }
    return MODEL_OK;
}

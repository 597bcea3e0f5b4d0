/*
 * se3sync plant: the RKMK4 step on SE(3) x R^6, written once for a number type REAL and
 * #included by model.c twice: REAL = double (one body) and, where the compiler has vector
 * extensions (GCC, Clang), REAL = a vector of two doubles (two bodies at once, one per lane).
 * Each lane performs the scalar code's operations in the same order (no FMA: -ffp-contract=off),
 * so both give the same bits; the pair runs ~1.6x faster per body on SSE2.
 *
 * Before including: REAL, SFX(name) (the instance's function names), BODYT (a struct with J[9],
 * Jinv[9], minv and u[6] of REAL) and EXPC(th2, &A, &B, &C) (the exp coefficients for REAL).
 * With RKMK4_DRAG defined, BODYT also has cv and cw (the drag coefficients) and the acceleration
 * includes -cv v / m and J^-1 (-cw w); the instances without it are the same code as before.
 */
static ALWAYS_INLINE void SFX(cross)(const REAL a[3], const REAL b[3], REAL c[3])
{
    c[0] = a[1] * b[2] - a[2] * b[1];
    c[1] = a[2] * b[0] - a[0] * b[2];
    c[2] = a[0] * b[1] - a[1] * b[0];
}

static ALWAYS_INLINE void SFX(mat3_vec)(const REAL M[9], const REAL x[3], REAL y[3])
{
    y[0] = M[0] * x[0] + M[1] * x[1] + M[2] * x[2];
    y[1] = M[3] * x[0] + M[4] * x[1] + M[5] * x[2];
    y[2] = M[6] * x[0] + M[7] * x[1] + M[8] * x[2];
}

static ALWAYS_INLINE void SFX(mat3T_vec)(const REAL M[9], const REAL x[3], REAL y[3])
{
    y[0] = M[0] * x[0] + M[3] * x[1] + M[6] * x[2];
    y[1] = M[1] * x[0] + M[4] * x[1] + M[7] * x[2];
    y[2] = M[2] * x[0] + M[5] * x[1] + M[8] * x[2];
}

/* body-frame acceleration a = I^{-1}(ad_xi^T I xi + u) + [0; R^T g] */
static ALWAYS_INLINE void SFX(accel)(const BODYT *B, const REAL xi[6], const REAL *gb, REAL a[6])
{
    const REAL *w = xi, *v = xi + 3;
    REAL Jw[3], t[3], vw[3];
    const REAL im = B->minv;
    SFX(mat3_vec)(B->J, w, Jw);
    SFX(cross)(Jw, w, t);
    t[0] += B->u[0];
    t[1] += B->u[1];
    t[2] += B->u[2];
#ifdef RKMK4_DRAG
    /* the optional drag terms (only in the instance compiled with RKMK4_DRAG): -c_w w, -c_v v */
    t[0] -= B->cw * w[0];
    t[1] -= B->cw * w[1];
    t[2] -= B->cw * w[2];
#endif
    SFX(mat3_vec)(B->Jinv, t, a);
    SFX(cross)(v, w, vw);
    a[3] = vw[0] + B->u[3] * im;
    a[4] = vw[1] + B->u[4] * im;
    a[5] = vw[2] + B->u[5] * im;
#ifdef RKMK4_DRAG
    a[3] -= B->cv * v[0] * im;
    a[4] -= B->cv * v[1] * im;
    a[5] -= B->cv * v[2] * im;
#endif
    if (gb) {
        a[3] += gb[0];
        a[4] += gb[1];
        a[5] += gb[2];
    }
}

/* Lie bracket on se(3): [a, b] = ad_a b = [wa x wb; wa x vb + va x wb] */
static ALWAYS_INLINE void SFX(bracket)(const REAL a[6], const REAL b[6], REAL c[6])
{
    REAL t1[3], t2[3];
    SFX(cross)(a, b, c);
    SFX(cross)(a, b + 3, t1);
    SFX(cross)(a + 3, b, t2);
    c[3] = t1[0] + t2[0];
    c[4] = t1[1] + t2[1];
    c[5] = t1[2] + t2[2];
}

/* dexp^{-1}_{-Theta}(xi) = xi + [Theta, xi]/2 + [Theta, [Theta, xi]]/12 (+ O(Theta^4)) */
static ALWAYS_INLINE void SFX(dexpinv)(const REAL th[6], const REAL xi[6], REAL out[6])
{
    REAL c1[6], c2[6];
    SFX(bracket)(th, xi, c1);
    SFX(bracket)(th, c1, c2);
#define DX(k) out[k] = xi[k] + 0.5 * c1[k] + c2[k] * (1.0 / 12.0);
    DX(0) DX(1) DX(2) DX(3) DX(4) DX(5)
#undef DX
}

/* gb = exp(phi)^T g0 (gravity in the frame of R0 exp(phi), given g0 = R0^T g) */
static ALWAYS_INLINE void SFX(rotate_gravity)(const REAL phi[3], const REAL g0[3], REAL gb[3])
{
    REAL A, B, C, c1[3], c2[3];
    EXPC(phi[0] * phi[0] + phi[1] * phi[1] + phi[2] * phi[2], &A, &B, &C);
    (void)C;
    SFX(cross)(phi, g0, c1);
    SFX(cross)(phi, c1, c2);
    for (int k = 0; k < 3; k++) gb[k] = g0[k] - A * c1[k] + B * c2[k];
}

/* X <- X exp(theta^) on SE(3); R <- R + R (exp(phi) - I) keeps the rounding small */
static ALWAYS_INLINE void SFX(se3_update)(REAL *p, REAL *R, const REAL th[6])
{
    const REAL *phi = th, *rho = th + 3;
    const REAL x = phi[0], y = phi[1], z = phi[2];
    const REAL th2 = x * x + y * y + z * z;
    REAL A, B, C, D[9], c1[3], c2[3], Vr[3], dp[3], Rn[9];
    EXPC(th2, &A, &B, &C);
    D[0] = -B * (y * y + z * z);
    D[1] = -A * z + B * x * y;
    D[2] = A * y + B * x * z;
    D[3] = A * z + B * x * y;
    D[4] = -B * (x * x + z * z);
    D[5] = -A * x + B * y * z;
    D[6] = -A * y + B * x * z;
    D[7] = A * x + B * y * z;
    D[8] = -B * (x * x + y * y);
    SFX(cross)(phi, rho, c1);
    SFX(cross)(phi, c1, c2);
    for (int k = 0; k < 3; k++) Vr[k] = rho[k] + B * c1[k] + C * c2[k];
    SFX(mat3_vec)(R, Vr, dp);
    p[0] += dp[0];
    p[1] += dp[1];
    p[2] += dp[2];
    for (int r = 0; r < 3; r++)
        for (int c = 0; c < 3; c++)
            Rn[3 * r + c] = R[3 * r + c]
                            + (R[3 * r] * D[c] + R[3 * r + 1] * D[3 + c] + R[3 * r + 2] * D[6 + c]);
    memcpy(R, Rn, sizeof Rn);
}

/* one RKMK4 step of length h for one body, or a pair in the vector instance (the 6-component
 * loops are unrolled by hand: gcc -O2 does not unroll them and they dominate the cost) */
static void SFX(rkmk4_step)(const BODYT *Bd, REAL *p, REAL *R, REAL *xi, const REAL *gw, double h)
{
    REAL g0[3], gb[3], *gp = NULL;
    REAL k1v[6], k2x[6], k2v[6], k3x[6], k3v[6], k4x[6], k4v[6], th[6], xs[6];
    const double h2 = 0.5 * h, h6 = h / 6.0;
    if (gw) {
        SFX(mat3T_vec)(R, gw, g0);
        gp = gb;
        memcpy(gb, g0, sizeof g0);
    }
    /* stage 1: Theta = 0, K1 = F(y0) */
    SFX(accel)(Bd, xi, gp, k1v);
    /* stage 2: Theta = h/2 K1 */
    th[0] = h2 * xi[0];
    xs[0] = xi[0] + h2 * k1v[0];
    th[1] = h2 * xi[1];
    xs[1] = xi[1] + h2 * k1v[1];
    th[2] = h2 * xi[2];
    xs[2] = xi[2] + h2 * k1v[2];
    th[3] = h2 * xi[3];
    xs[3] = xi[3] + h2 * k1v[3];
    th[4] = h2 * xi[4];
    xs[4] = xi[4] + h2 * k1v[4];
    th[5] = h2 * xi[5];
    xs[5] = xi[5] + h2 * k1v[5];
    if (gw) SFX(rotate_gravity)(th, g0, gb);
    SFX(dexpinv)(th, xs, k2x);
    SFX(accel)(Bd, xs, gp, k2v);
    /* stage 3: Theta = h/2 K2 */
    th[0] = h2 * k2x[0];
    xs[0] = xi[0] + h2 * k2v[0];
    th[1] = h2 * k2x[1];
    xs[1] = xi[1] + h2 * k2v[1];
    th[2] = h2 * k2x[2];
    xs[2] = xi[2] + h2 * k2v[2];
    th[3] = h2 * k2x[3];
    xs[3] = xi[3] + h2 * k2v[3];
    th[4] = h2 * k2x[4];
    xs[4] = xi[4] + h2 * k2v[4];
    th[5] = h2 * k2x[5];
    xs[5] = xi[5] + h2 * k2v[5];
    if (gw) SFX(rotate_gravity)(th, g0, gb);
    SFX(dexpinv)(th, xs, k3x);
    SFX(accel)(Bd, xs, gp, k3v);
    /* stage 4: Theta = h K3 */
    th[0] = h * k3x[0];
    xs[0] = xi[0] + h * k3v[0];
    th[1] = h * k3x[1];
    xs[1] = xi[1] + h * k3v[1];
    th[2] = h * k3x[2];
    xs[2] = xi[2] + h * k3v[2];
    th[3] = h * k3x[3];
    xs[3] = xi[3] + h * k3v[3];
    th[4] = h * k3x[4];
    xs[4] = xi[4] + h * k3v[4];
    th[5] = h * k3x[5];
    xs[5] = xi[5] + h * k3v[5];
    if (gw) SFX(rotate_gravity)(th, g0, gb);
    SFX(dexpinv)(th, xs, k4x);
    SFX(accel)(Bd, xs, gp, k4v);
    /* update */
    th[0] = h6 * (xi[0] + 2.0 * k2x[0] + 2.0 * k3x[0] + k4x[0]);
    xs[0] = xi[0] + h6 * (k1v[0] + 2.0 * k2v[0] + 2.0 * k3v[0] + k4v[0]);
    th[1] = h6 * (xi[1] + 2.0 * k2x[1] + 2.0 * k3x[1] + k4x[1]);
    xs[1] = xi[1] + h6 * (k1v[1] + 2.0 * k2v[1] + 2.0 * k3v[1] + k4v[1]);
    th[2] = h6 * (xi[2] + 2.0 * k2x[2] + 2.0 * k3x[2] + k4x[2]);
    xs[2] = xi[2] + h6 * (k1v[2] + 2.0 * k2v[2] + 2.0 * k3v[2] + k4v[2]);
    th[3] = h6 * (xi[3] + 2.0 * k2x[3] + 2.0 * k3x[3] + k4x[3]);
    xs[3] = xi[3] + h6 * (k1v[3] + 2.0 * k2v[3] + 2.0 * k3v[3] + k4v[3]);
    th[4] = h6 * (xi[4] + 2.0 * k2x[4] + 2.0 * k3x[4] + k4x[4]);
    xs[4] = xi[4] + h6 * (k1v[4] + 2.0 * k2v[4] + 2.0 * k3v[4] + k4v[4]);
    th[5] = h6 * (xi[5] + 2.0 * k2x[5] + 2.0 * k3x[5] + k4x[5]);
    xs[5] = xi[5] + h6 * (k1v[5] + 2.0 * k2v[5] + 2.0 * k3v[5] + k4v[5]);
    SFX(se3_update)(p, R, th);
    memcpy(xi, xs, sizeof xs);
}


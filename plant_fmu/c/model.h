/*
 * se3sync plant: N rigid bodies on SE(3) -- model equations, integrator and parameter
 * validation.  This file knows nothing about FMI; fmi2.c wraps it.
 *
 * Per body (body frame velocity xi = [w; v], wrench u = [tau; f]):
 *     dX/dt = X xi^                  (X = [[R, p], [0, 1]])
 *     J dw/dt = (J w) x w + tau
 *     m dv/dt = m v x w + f + m R^T g
 *
 * Integrator: Runge-Kutta-Munthe-Kaas of order 4 (classical RK4 tableau) on the group
 * SE(3) x R^6, with dexp^{-1} truncated after the second commutator.  See docs/reference/plant-fmu.md.
 */
#ifndef SE3SYNC_MODEL_H
#define SE3SYNC_MODEL_H

#include <stddef.h>

#include "config.h" /* N_BODIES and FMU_GUID (generated into the FMU's sources/) */
#ifndef N_BODIES
#define N_BODIES 1
#endif
#ifndef FMU_GUID
#define FMU_GUID "{00000000-0000-0000-0000-000000000000}"
#endif

#if N_BODIES < 1
#error "N_BODIES must be >= 1"
#endif

/* ---- value reference layout (fixed contract, mirrored by plant_fmu/layout.py) ---- */
#define VR_GRAVITY      1u   /* g[1..3] at 1..3 */
#define VR_H_INTERNAL   4u
/* optional plant terms (all off by default; off, the model runs exactly the code it ran without them) */
#define VR_GROUND        5u  /* 1: a ground plane (needs g != 0: "up" is -g/|g|), 0: none */
#define VR_GROUND_HEIGHT 6u  /* the plane's height along up, m */
#define VR_DRAG_LINEAR   7u  /* linear drag on the body velocity, N s/m */
#define VR_DRAG_ANGULAR  8u  /* linear drag on the angular rate, N m s/rad */
#define VR_GLOBAL_LAST   8u
#define VR_BODY_BASE    1000u
#define VR_BODY_STRIDE  100u

#define OFF_P    0   /* p[3]  */
#define OFF_R    3   /* R[9] row-major */
#define OFF_XI   12  /* xi[6] = [w; v] */
#define OFF_Q    18  /* q[4], w first, w >= 0 */
#define OFF_CONTACT 22 /* 1 while the body rests on the ground, else 0 */
#define N_OUT    23
#define OFF_U    30  /* u[6] = [tau; f] */
#define N_U      6
#define OFF_PAR  40  /* parameters: m, J[9], p0[3], q0[4], xi0[6] */
#define N_PAR    23
#define PAR_M    0
#define PAR_J    1
#define PAR_P0   10
#define PAR_Q0   13
#define PAR_XI0  17

/* ---- accepted ranges (see docs/reference/plant-fmu.md, "Limits") ---- */
/* h_internal below this is refused (at exitInitializationMode and in a deserialized state) */
#define H_INTERNAL_MIN 1e-9
/* work budget of one doStep: N_BODIES x substeps <= this, else the call is refused before any
 * work is done.  One body-substep costs about 0.15-0.3 us, so the worst accepted call takes
 * 0.15-0.3 s whatever N_BODIES is. */
#define MAX_BODY_SUBSTEPS 1000000LL
/* the principal moments of J and the mass m must lie in [MAG_MIN, MAG_MAX]: then J, J^-1, m and
 * 1/m are finite and normal with a margin of 1e58 for the products J w x w, J^-1 tau and f / m */
#define MAG_MIN 1e-250
#define MAG_MAX 1e250
/* |R^T R - I| (max entry) allowed in a deserialized state */
#define R_ORTHO_TOL 1e-6

/* status codes of the model layer (numerically equal to fmi2OK / fmi2Warning / fmi2Error) */
#define MODEL_OK      0
#define MODEL_WARNING 1
#define MODEL_ERROR   3

typedef struct {
    double out[N_OUT];  /* p, R (row-major), xi, q -- the state and its outputs */
    double u[N_U];      /* input wrench, body frame, held constant over a step */
    double par[N_PAR];  /* parameters as set by the importer */
    double J[9];        /* symmetrised inertia (valid after model_initialize) */
    double Jinv[9];     /* its inverse */
    double minv;        /* 1 / m */
} Body;

typedef struct {
    double g[3];        /* gravity, world frame */
    double h_internal;  /* internal integration step */
    double ground;      /* 1: ground plane on, 0: off */
    double ground_height; /* the plane: {p : e_up . p = ground_height}, e_up = -g/|g| */
    double drag_linear; /* f_drag = -drag_linear v (body frame) */
    double drag_angular; /* tau_drag = -drag_angular w */
    double time;        /* current time */
    int q_valid;        /* quaternion outputs up to date with R */
    Body body[N_BODIES];
} ModelData;

/* kinds of variables returned by model_lookup */
enum { VAR_UNKNOWN = 0, VAR_OUTPUT, VAR_INPUT, VAR_PARAMETER };

typedef void (*ModelLogger)(void *env, int status, const char *category, const char *message);

void model_set_defaults(ModelData *d);

/* Pointer to the Real variable with value reference vr, or NULL; *kind receives its kind. */
double *model_lookup(ModelData *d, unsigned int vr, int *kind);

/* Like model_lookup for vr[0], and *run receives how many of vr[0..nvr-1] are consecutive
 * value references stored consecutively from the returned pointer (same kind); *offset is
 * the offset of vr[0] within its block (body variables: 0..99). */
double *model_lookup_run(ModelData *d, const unsigned int *vr, size_t nvr, int *kind, size_t *run,
                         unsigned int *offset);

/* Writes the structured name of vr (e.g. "body[2].u[4]") into buf. */
void model_variable_name(unsigned int vr, char *buf, size_t n);

/* Validates every parameter and, if valid, sets the state from the initial values.
 * Returns MODEL_OK, MODEL_WARNING (something was corrected, e.g. q0 normalised) or
 * MODEL_ERROR (nothing changed); each problem is reported through log. */
int model_initialize(ModelData *d, ModelLogger log, void *env);

/* Checks a state restored from outside (a deserialized FMU state): everything finite, h_internal
 * within bounds; if `initialized`, also every parameter as model_initialize does, the derived
 * J, J^-1, 1/m equal to what model_initialize computes from them (bit for bit) and R orthonormal
 * within R_ORTHO_TOL with det R > 0; if `may_be_non_finite` (a state after a failed step), the
 * outputs are not checked.  Returns MODEL_OK or MODEL_ERROR (each problem logged). */
int model_validate_state(const ModelData *d, int initialized, int may_be_non_finite, ModelLogger log, void *env);

/* State and outputs computed from the current parameters without validation
 * (used to answer fmi2GetReal during initialization mode). */
void model_preview(ModelData *d);

/* MODEL_OK if a step of h is within the work budget (N_BODIES * substeps <= MAX_BODY_SUBSTEPS),
 * else MODEL_ERROR with a logged message naming the limit. */
int model_check_step(const ModelData *d, double h, ModelLogger log, void *env);

/* Advances all bodies by h (h > 0 checked by the caller) in n = ceil(h/h_internal - 1e-9)
 * equal substeps.  Returns MODEL_ERROR without doing anything if N_BODIES * n exceeds
 * MAX_BODY_SUBSTEPS, and MODEL_ERROR (state not finite, unusable) if the result is not finite. */
int model_do_step(ModelData *d, double h, ModelLogger log, void *env);

/* brings the quaternion outputs up to date (they are computed on demand) */
void model_update_quaternions(ModelData *d);

/* quaternion (w first, w >= 0) of a rotation matrix, Shepperd's method */
void model_quat_from_R(const double R[9], double q[4]);

#endif

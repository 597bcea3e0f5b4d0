/*
 * se3sync plant: the part of the Co-Simulation interface that does not depend on the FMI
 * version -- instance data, logging and log categories, the call-sequence state machine,
 * Float64 get/set by value reference, FMU state snapshots and their serialization.
 * fmi2.c (FMI 2.0) and fmi3.c (FMI 3.0) are thin adapters over it and model.c.
 *
 * fmu_common.c is compiled as part of each layer (fmi2.c and fmi3.c #include it), so the
 * FMU's sources are still model.c + fmiN.c and these functions stay internal (static) to
 * the shared library.  Every function takes the name of the FMI function it serves (for
 * messages) and returns an FmuStatus, which each layer maps to its own status type.
 */
#ifndef SE3SYNC_FMU_COMMON_H
#define SE3SYNC_FMU_COMMON_H

#include <stddef.h>
#include <stdint.h>

#include "model.h"

/* internal status, numerically equal to fmi2Status/fmi3Status OK..Fatal and to MODEL_* */
typedef enum { FMU_OK = 0, FMU_WARNING = 1, FMU_DISCARD = 2, FMU_ERROR = 3, FMU_FATAL = 4 } FmuStatus;

typedef enum {
    M_INSTANTIATED = 1 << 0,
    M_INIT = 1 << 1,
    M_STEP_COMPLETE = 1 << 2, /* FMI 3.0 "Step Mode" */
    M_STEP_FAILED = 1 << 3,
    M_TERMINATED = 1 << 4
} FmuMode;

#define M_ANY (M_INSTANTIATED | M_INIT | M_STEP_COMPLETE | M_STEP_FAILED | M_TERMINATED)
#define GET_MODES M_ANY
#define SET_MODES (M_INSTANTIATED | M_INIT | M_STEP_COMPLETE)
#define STATE_MODES M_ANY

/* log categories (bit flags) */
#define CAT_EVENTS   (1u << 0)
#define CAT_WARNING  (1u << 1)
#define CAT_DISCARD  (1u << 2)
#define CAT_ERROR    (1u << 3)
#define CAT_FATAL    (1u << 4)
#define CAT_CALLS    (1u << 5)
#define CAT_ALL      0x3fu

/* everything an FMU state holds (also the payload of a serialized state) */
typedef struct {
    FmuMode mode;
    ModelData data;
} FmuSnapshot;

typedef struct FmuInstance FmuInstance;

/* What differs between the FMI versions (one constant per layer). */
typedef struct {
    /* hands a formatted message (a writable buffer) to the importer's logger */
    void (*emit)(FmuInstance *c, FmuStatus status, const char *category, char *message);
    const char *step_mode_name;    /* name of M_STEP_COMPLETE in messages */
    const char *state_arg;         /* name of the FMU state argument in messages */
    const char *state_description; /* "not a serialized <this> state" */
    uint32_t serial_version;       /* serialized states of the other layer are refused */
    int has_time_vr;               /* value reference 0 is the independent variable time */
} FmuLayer;

/* The version-independent part of an instance; each layer's instance struct starts with it. */
struct FmuInstance {
    /* unused: malloc implementations keep their free-list links in the first bytes of a freed
     * block (glibc: up to 32), so the fields read to detect and log a double free come after */
    unsigned char reserved_[32];
    const FmuLayer *layer;
    char *name;
    uint64_t magic; /* FMU_MAGIC_LIVE from instantiate to free, then FMU_MAGIC_FREED */
    int logging_on;
    unsigned int categories;
    FmuMode mode;
    double start_time;
    FmuSnapshot s; /* s.mode mirrors mode on get */
};

#define FMU_VR_TIME 0u

/* Instance markers.  A call with an instance whose magic is not FMU_MAGIC_LIVE returns an error
 * without touching it; FMU_MAGIC_FREED (a freed instance whose memory has not been reused yet)
 * is also logged.  This is a best-effort guard: reading a freed or garbage pointer is undefined
 * behaviour in C (see docs/reference/plant-fmu.md, "Limits"). */
#define FMU_MAGIC_LIVE  0x5345335359e1c0deULL
#define FMU_MAGIC_FREED 0x5345335346524545ULL

/* the instance is live (logs and returns 0 for a freed one, returns 0 for NULL or garbage) */
static int fmu_live(FmuInstance *c, const char *fn);

/* ---- logging */
static void fmu_log(FmuInstance *c, FmuStatus status, const char *category, const char *fmt, ...);
#define FMU_LOG_ERROR(c, ...) fmu_log((c), FMU_ERROR, "logStatusError", __VA_ARGS__)
/* ModelLogger handed to model.c (env is the FmuInstance) */
static void fmu_model_logger(void *env, int status, const char *category, const char *message);
static FmuStatus fmu_set_debug_logging(FmuInstance *c, const char *fn, int loggingOn, size_t nCategories,
                                       const char *const categories[]);

/* ---- life cycle */
/* allocates a zeroed instance of `size` bytes (>= sizeof(FmuInstance)) with a copy of name;
 * NULL if out of memory */
static FmuInstance *fmu_alloc(size_t size, const char *name, const FmuLayer *layer, int loggingOn);
/* frees a live instance; a freed one is logged and ignored (best effort, see fmu_live) */
static void fmu_free(FmuInstance *c, const char *fn);
/* NULL-instance guard and call-sequence check (logs the illegal call) */
static int fmu_allowed(FmuInstance *c, const char *fn, unsigned int modes);
static FmuStatus fmu_unsupported(FmuInstance *c, const char *fn, const char *why);
static FmuStatus fmu_check_experiment(FmuInstance *c, const char *fn, double startTime, int stopTimeDefined,
                                      double stopTime);
static void fmu_enter_initialization_mode(FmuInstance *c);
static FmuStatus fmu_exit_initialization_mode(FmuInstance *c, const char *fn);
static FmuStatus fmu_terminate(FmuInstance *c, const char *fn);
static FmuStatus fmu_reset(FmuInstance *c, const char *fn);
/* validates the arguments and advances the model; a failed step leaves M_STEP_FAILED */
static FmuStatus fmu_do_step(FmuInstance *c, const char *fn, double currentCommunicationPoint,
                             double communicationStepSize);

/* ---- get / set (vr and values non-NULL, nvr > 0: checked by the layer) */
static FmuStatus fmu_get_float64(FmuInstance *c, const char *fn, const unsigned int vr[], size_t nvr,
                                 double values[]);
/* checks everything first: a refused call changes nothing */
static FmuStatus fmu_set_float64(FmuInstance *c, const char *fn, const unsigned int vr[], size_t nvr,
                                 const double values[]);
/* the get/set functions of types the FMU has no variables of */
static FmuStatus fmu_no_variables(FmuInstance *c, const char *fn, size_t nvr, const unsigned int vr[],
                                  const char *why);

/* ---- FMU state */
static FmuStatus fmu_get_state(FmuInstance *c, const char *fn, void **state);
static FmuStatus fmu_set_state(FmuInstance *c, const char *fn, void *state);
static FmuStatus fmu_free_state(FmuInstance *c, const char *fn, void **state);
static FmuStatus fmu_serialized_state_size(FmuInstance *c, const char *fn, void *state, size_t *size);
static FmuStatus fmu_serialize_state(FmuInstance *c, const char *fn, void *state, void *buffer, size_t size);
static FmuStatus fmu_deserialize_state(FmuInstance *c, const char *fn, const void *buffer, size_t size,
                                       void **state);

#endif

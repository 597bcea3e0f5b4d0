/*
 * se3sync plant: the version-independent part of the Co-Simulation interface (see
 * fmu_common.h).  #included by fmi2.c and fmi3.c; no global or static mutable data.
 */
#include <math.h>
#include <stdarg.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "fmu_common.h"

static const struct {
    const char *name;
    unsigned int flag;
} CATEGORIES[] = {
    {"logEvents", CAT_EVENTS},         {"logStatusWarning", CAT_WARNING}, {"logStatusDiscard", CAT_DISCARD},
    {"logStatusError", CAT_ERROR},     {"logStatusFatal", CAT_FATAL},     {"logCalls", CAT_CALLS},
    {"logAll", CAT_ALL},
};
#define N_CATEGORIES (sizeof CATEGORIES / sizeof CATEGORIES[0])

/* Header of a serialized state (all fields native-endian, like the payload).  The version tells
 * the FMI 2.0 and 3.0 layers' states apart; format is the layout of header + payload; checksum
 * is FNV-1a (64 bit) of the whole serialized state with the checksum field set to 0. */
#define SERIAL_MAGIC "SE3SYNC\x02"
#define SERIAL_FORMAT 3u

typedef struct {
    char magic[8];
    uint32_t version;
    uint32_t format;
    uint32_t n_bodies;
    uint32_t header_size;
    uint64_t size;     /* of header + payload */
    uint64_t checksum;
} SerialHeader;

#define SERIAL_SIZE (sizeof(SerialHeader) + sizeof(FmuSnapshot))

/* ------------------------------------------------------------------ logging */

static unsigned int fmu_category_flag(const char *category)
{
    for (size_t k = 0; k < N_CATEGORIES; k++)
        if (strcmp(category, CATEGORIES[k].name) == 0) return CATEGORIES[k].flag;
    return 0;
}

static void fmu_vlog(FmuInstance *c, FmuStatus status, const char *category, const char *fmt, va_list ap)
{
    char buf[1024];
    if (!c || (c->magic != FMU_MAGIC_LIVE && c->magic != FMU_MAGIC_FREED)) return;
    /* warnings and errors are always reported; other messages only when enabled */
    if (status < FMU_WARNING && !(c->logging_on && (c->categories & fmu_category_flag(category)))) return;
    vsnprintf(buf, sizeof buf, fmt, ap);
    c->layer->emit(c, status, category, buf);
}

static void fmu_log(FmuInstance *c, FmuStatus status, const char *category, const char *fmt, ...)
{
    va_list ap;
    va_start(ap, fmt);
    fmu_vlog(c, status, category, fmt, ap);
    va_end(ap);
}

static void fmu_model_logger(void *env, int status, const char *category, const char *message)
{
    fmu_log((FmuInstance *)env, (FmuStatus)status, category, "%s", message);
}

static FmuStatus fmu_set_debug_logging(FmuInstance *c, const char *fn, int loggingOn, size_t nCategories,
                                       const char *const categories[])
{
    unsigned int mask = 0;
    if (!fmu_allowed(c, fn, M_ANY)) return FMU_ERROR;
    if (nCategories > 0 && !categories) {
        FMU_LOG_ERROR(c, "%s: categories is NULL", fn);
        return FMU_ERROR;
    }
    for (size_t k = 0; k < nCategories; k++) {
        unsigned int f = categories[k] ? fmu_category_flag(categories[k]) : 0;
        if (!f) {
            FMU_LOG_ERROR(c, "%s: unknown log category '%s'", fn, categories[k] ? categories[k] : "(null)");
            return FMU_ERROR;
        }
        mask |= f;
    }
    c->logging_on = loggingOn;
    c->categories = nCategories == 0 ? CAT_ALL : mask;
    return FMU_OK;
}

/* ------------------------------------------------------------------ life cycle */

static FmuInstance *fmu_alloc(size_t size, const char *name, const FmuLayer *layer, int loggingOn)
{
    FmuInstance *c = (FmuInstance *)calloc(1, size);
    if (c) c->name = (char *)malloc(strlen(name) + 1);
    if (!c || !c->name) {
        if (c) free(c);
        return NULL;
    }
    strcpy(c->name, name);
    c->magic = FMU_MAGIC_LIVE;
    c->layer = layer;
    c->logging_on = loggingOn;
    c->categories = CAT_ALL;
    c->mode = M_INSTANTIATED;
    model_set_defaults(&c->s.data);
    return c;
}

static int fmu_live(FmuInstance *c, const char *fn)
{
    if (!c) return 0;
    if (c->magic == FMU_MAGIC_LIVE) return 1;
    if (c->magic == FMU_MAGIC_FREED) /* the layer's logger and env are still in the (freed) block */
        fmu_log(c, FMU_ERROR, "logStatusError", "%s: called with an instance that was already freed (ignored)", fn);
    return 0;
}

static void fmu_free(FmuInstance *c, const char *fn)
{
    if (!fmu_live(c, fn)) return;
    /* volatile: the compiler would otherwise drop these stores as dead (the block is freed next) */
    *(volatile uint64_t *)&c->magic = FMU_MAGIC_FREED;
    free(c->name);
    *(char *volatile *)&c->name = NULL; /* emit2/emit3 print "" for a NULL name */
    free(c);
}

static const char *fmu_mode_name(const FmuInstance *c)
{
    switch (c->mode) {
    case M_INSTANTIATED: return "instantiated";
    case M_INIT: return "initialization mode";
    case M_STEP_COMPLETE: return c->layer->step_mode_name;
    case M_STEP_FAILED: return "step failed";
    case M_TERMINATED: return "terminated";
    }
    return "?";
}

static int fmu_allowed(FmuInstance *c, const char *fn, unsigned int modes)
{
    if (!fmu_live(c, fn)) return 0;
    if (c->mode & modes) return 1;
    FMU_LOG_ERROR(c, "%s: illegal call in state '%s'", fn, fmu_mode_name(c));
    return 0;
}

static FmuStatus fmu_unsupported(FmuInstance *c, const char *fn, const char *why)
{
    if (!fmu_live(c, fn)) return FMU_ERROR;
    FMU_LOG_ERROR(c, "%s: not supported (%s)", fn, why);
    return FMU_ERROR;
}

static FmuStatus fmu_check_experiment(FmuInstance *c, const char *fn, double startTime, int stopTimeDefined,
                                      double stopTime)
{
    if (!isfinite(startTime)) {
        FMU_LOG_ERROR(c, "%s: startTime = %g is not finite", fn, startTime);
        return FMU_ERROR;
    }
    if (stopTimeDefined && !(stopTime >= startTime)) {
        FMU_LOG_ERROR(c, "%s: stopTime = %g is before startTime = %g", fn, stopTime, startTime);
        return FMU_ERROR;
    }
    return FMU_OK;
}

static void fmu_enter_initialization_mode(FmuInstance *c)
{
    c->mode = M_INIT;
    model_preview(&c->s.data);
}

static FmuStatus fmu_exit_initialization_mode(FmuInstance *c, const char *fn)
{
    int st;
    if (!fmu_allowed(c, fn, M_INIT)) return FMU_ERROR;
    st = model_initialize(&c->s.data, fmu_model_logger, c);
    if (st == MODEL_ERROR) {
        FMU_LOG_ERROR(c, "%s: invalid parameters (see the messages above); still in initialization mode", fn);
        return FMU_ERROR;
    }
    c->s.data.time = c->start_time;
    c->mode = M_STEP_COMPLETE; /* Co-Simulation without event mode: Step Mode */
    return st == MODEL_WARNING ? FMU_WARNING : FMU_OK;
}

static FmuStatus fmu_terminate(FmuInstance *c, const char *fn)
{
    if (!fmu_allowed(c, fn, M_STEP_COMPLETE | M_STEP_FAILED)) return FMU_ERROR;
    c->mode = M_TERMINATED;
    return FMU_OK;
}

static FmuStatus fmu_reset(FmuInstance *c, const char *fn)
{
    if (!fmu_allowed(c, fn, M_ANY)) return FMU_ERROR;
    c->mode = M_INSTANTIATED;
    c->start_time = 0.0;
    model_set_defaults(&c->s.data);
    return FMU_OK;
}

static FmuStatus fmu_do_step(FmuInstance *c, const char *fn, double currentCommunicationPoint,
                             double communicationStepSize)
{
    if (!isfinite(communicationStepSize) || !(communicationStepSize > 0.0)) {
        FMU_LOG_ERROR(c, "%s: communicationStepSize = %g must be finite and > 0", fn, communicationStepSize);
        return FMU_ERROR;
    }
    if (!isfinite(currentCommunicationPoint)) {
        FMU_LOG_ERROR(c, "%s: currentCommunicationPoint = %g is not finite", fn, currentCommunicationPoint);
        return FMU_ERROR;
    }
    /* over the work budget: refused before any work, the instance stays usable */
    if (model_check_step(&c->s.data, communicationStepSize, fmu_model_logger, c) != MODEL_OK) {
        FMU_LOG_ERROR(c, "%s: step from t = %g refused (nothing was done)", fn, currentCommunicationPoint);
        return FMU_ERROR;
    }
    if (model_do_step(&c->s.data, communicationStepSize, fmu_model_logger, c) != MODEL_OK) {
        c->mode = M_STEP_FAILED;
        FMU_LOG_ERROR(c, "%s: step from t = %g failed", fn, currentCommunicationPoint);
        return FMU_ERROR;
    }
    c->s.data.time = currentCommunicationPoint + communicationStepSize;
    return FMU_OK;
}

/* ------------------------------------------------------------------ get / set */

static FmuStatus fmu_get_float64(FmuInstance *c, const char *fn, const unsigned int vr[], size_t nvr,
                                 double values[])
{
    ModelData *d = &c->s.data;
    if (c->mode & (M_INSTANTIATED | M_INIT)) model_preview(d);
    for (size_t k = 0, run; k < nvr; k += run) {
        int kind;
        unsigned int off;
        const double *p;
        if (c->layer->has_time_vr && vr[k] == FMU_VR_TIME) {
            values[k] = d->time;
            run = 1;
            continue;
        }
        p = model_lookup_run(d, vr + k, nvr - k, &kind, &run, &off);
        if (!p) {
            FMU_LOG_ERROR(c, "%s: unknown value reference %u", fn, (unsigned)vr[k]);
            return FMU_ERROR;
        }
        if (kind == VAR_OUTPUT && !d->q_valid && off < OFF_Q + 4 && off + run > OFF_Q)
            model_update_quaternions(d); /* quaternions are computed on demand */
        memcpy(values + k, p, run * sizeof(double));
    }
    return FMU_OK;
}

static FmuStatus fmu_set_float64(FmuInstance *c, const char *fn, const unsigned int vr[], size_t nvr,
                                 const double values[])
{
    ModelData *d = &c->s.data;
    char name[64];
    /* check everything first: a refused call changes nothing */
    for (size_t k = 0, run; k < nvr; k += run) {
        int kind;
        unsigned int off;
        if (c->layer->has_time_vr && vr[k] == FMU_VR_TIME) {
            FMU_LOG_ERROR(c, "%s: time (value reference 0) is the independent variable and cannot be set", fn);
            return FMU_ERROR;
        }
        (void)model_lookup_run(d, vr + k, nvr - k, &kind, &run, &off);
        if (kind == VAR_UNKNOWN) {
            FMU_LOG_ERROR(c, "%s: unknown value reference %u", fn, (unsigned)vr[k]);
            return FMU_ERROR;
        }
        if (kind == VAR_OUTPUT) {
            model_variable_name(vr[k], name, sizeof name);
            FMU_LOG_ERROR(c, "%s: %s (value reference %u) is an output and cannot be set", fn, name,
                          (unsigned)vr[k]);
            return FMU_ERROR;
        }
        if (kind == VAR_PARAMETER && c->mode == M_STEP_COMPLETE) {
            model_variable_name(vr[k], name, sizeof name);
            FMU_LOG_ERROR(c, "%s: %s (value reference %u) is a fixed parameter and cannot be set after "
                             "initialization", fn, name, (unsigned)vr[k]);
            return FMU_ERROR;
        }
        for (size_t j = k; j < k + run; j++) {
            if (!isfinite(values[j])) {
                model_variable_name(vr[j], name, sizeof name);
                FMU_LOG_ERROR(c, "%s: %s = %g is not finite (value reference %u)", fn, name, values[j],
                              (unsigned)vr[j]);
                return FMU_ERROR;
            }
        }
    }
    for (size_t k = 0, run; k < nvr; k += run) {
        int kind;
        unsigned int off;
        double *p = model_lookup_run(d, vr + k, nvr - k, &kind, &run, &off);
        memcpy(p, values + k, run * sizeof(double));
    }
    return FMU_OK;
}

static FmuStatus fmu_no_variables(FmuInstance *c, const char *fn, size_t nvr, const unsigned int vr[],
                                  const char *why)
{
    if (nvr == 0) return FMU_OK;
    FMU_LOG_ERROR(c, "%s: unknown value reference %u (%s)", fn, vr ? (unsigned)vr[0] : 0u, why);
    return FMU_ERROR;
}

/* ------------------------------------------------------------------ FMU state */

/* the given snapshot, or a new one if it is NULL (NULL, logged, if out of memory) */
static FmuSnapshot *snapshot_for(FmuInstance *c, const char *fn, void *state)
{
    FmuSnapshot *s = (FmuSnapshot *)state;
    if (!s) {
        s = (FmuSnapshot *)malloc(sizeof *s);
        if (!s) FMU_LOG_ERROR(c, "%s: out of memory", fn);
    }
    return s;
}

static FmuStatus fmu_get_state(FmuInstance *c, const char *fn, void **state)
{
    FmuSnapshot *s;
    if (!fmu_allowed(c, fn, STATE_MODES)) return FMU_ERROR;
    if (!state) {
        FMU_LOG_ERROR(c, "%s: %s is NULL", fn, c->layer->state_arg);
        return FMU_ERROR;
    }
    s = snapshot_for(c, fn, *state);
    if (!s) return FMU_ERROR;
    c->s.mode = c->mode;
    memcpy(s, &c->s, sizeof *s);
    *state = s;
    return FMU_OK;
}

static FmuStatus fmu_set_state(FmuInstance *c, const char *fn, void *state)
{
    if (!fmu_allowed(c, fn, STATE_MODES)) return FMU_ERROR;
    if (!state) {
        FMU_LOG_ERROR(c, "%s: %s is NULL", fn, c->layer->state_arg);
        return FMU_ERROR;
    }
    memcpy(&c->s, state, sizeof c->s);
    c->mode = c->s.mode;
    return FMU_OK;
}

static FmuStatus fmu_free_state(FmuInstance *c, const char *fn, void **state)
{
    if (!fmu_allowed(c, fn, M_ANY)) return FMU_ERROR;
    if (!state) return FMU_OK;
    free(*state);
    *state = NULL;
    return FMU_OK;
}

static FmuStatus fmu_serialized_state_size(FmuInstance *c, const char *fn, void *state, size_t *size)
{
    if (!fmu_allowed(c, fn, M_ANY)) return FMU_ERROR;
    if (!state || !size) {
        FMU_LOG_ERROR(c, "%s: NULL argument", fn);
        return FMU_ERROR;
    }
    *size = SERIAL_SIZE;
    return FMU_OK;
}

/* FNV-1a, 64 bit (Fowler, Noll, Vo): a few lines, no dependency; it detects corruption, it is
 * not a protection against a deliberate forgery (the semantic checks below are) */
static uint64_t fnv1a64(uint64_t h, const unsigned char *p, size_t n)
{
    for (size_t k = 0; k < n; k++) {
        h ^= p[k];
        h *= 0x100000001b3ULL;
    }
    return h;
}

#define FNV1A64_INIT 0xcbf29ce484222325ULL

static uint64_t serial_checksum(const SerialHeader *h, const void *payload)
{
    SerialHeader z = *h;
    z.checksum = 0;
    return fnv1a64(fnv1a64(FNV1A64_INIT, (const unsigned char *)&z, sizeof z), (const unsigned char *)payload,
                   sizeof(FmuSnapshot));
}

static FmuStatus fmu_serialize_state(FmuInstance *c, const char *fn, void *state, void *buffer, size_t size)
{
    SerialHeader h;
    if (!fmu_allowed(c, fn, M_ANY)) return FMU_ERROR;
    if (!state || !buffer) {
        FMU_LOG_ERROR(c, "%s: NULL argument", fn);
        return FMU_ERROR;
    }
    if (size < SERIAL_SIZE) {
        FMU_LOG_ERROR(c, "%s: buffer of %lu bytes is too small (need %lu)", fn, (unsigned long)size,
                      (unsigned long)SERIAL_SIZE);
        return FMU_ERROR;
    }
    memset(&h, 0, sizeof h);
    memcpy(h.magic, SERIAL_MAGIC, 8);
    h.version = c->layer->serial_version;
    h.format = SERIAL_FORMAT;
    h.n_bodies = (uint32_t)N_BODIES;
    h.header_size = (uint32_t)sizeof h;
    h.size = (uint64_t)SERIAL_SIZE;
    h.checksum = serial_checksum(&h, state);
    memcpy(buffer, &h, sizeof h);
    memcpy((unsigned char *)buffer + sizeof h, state, sizeof(FmuSnapshot));
    return FMU_OK;
}

/* exactly one of the modes */
static int valid_mode(FmuMode m)
{
    return m == M_INSTANTIATED || m == M_INIT || m == M_STEP_COMPLETE || m == M_STEP_FAILED || m == M_TERMINATED;
}

static FmuStatus fmu_deserialize_state(FmuInstance *c, const char *fn, const void *buffer, size_t size,
                                       void **state)
{
    SerialHeader h;
    FmuSnapshot *s;
    int initialized;
    if (!fmu_allowed(c, fn, M_ANY)) return FMU_ERROR;
    if (!buffer || !state) {
        FMU_LOG_ERROR(c, "%s: NULL argument", fn);
        return FMU_ERROR;
    }
    if (size < sizeof h) {
        FMU_LOG_ERROR(c, "%s: %lu bytes is too short for a serialized state", fn, (unsigned long)size);
        return FMU_ERROR;
    }
    memcpy(&h, buffer, sizeof h);
    if (memcmp(h.magic, SERIAL_MAGIC, 8) != 0 || h.version != c->layer->serial_version
        || h.format != SERIAL_FORMAT || h.header_size != (uint32_t)sizeof h) {
        FMU_LOG_ERROR(c, "%s: not a serialized %s state (bad magic, version or format)", fn,
                      c->layer->state_description);
        return FMU_ERROR;
    }
    if (h.n_bodies != (uint32_t)N_BODIES) {
        FMU_LOG_ERROR(c, "%s: state of a %u-body FMU, this FMU has %d bodies", fn, (unsigned)h.n_bodies, N_BODIES);
        return FMU_ERROR;
    }
    if (size != SERIAL_SIZE || h.size != (uint64_t)SERIAL_SIZE) {
        FMU_LOG_ERROR(c, "%s: size %lu does not match the expected %lu bytes (truncated?)", fn, (unsigned long)size,
                      (unsigned long)SERIAL_SIZE);
        return FMU_ERROR;
    }
    if (serial_checksum(&h, (const unsigned char *)buffer + sizeof h) != h.checksum) {
        FMU_LOG_ERROR(c, "%s: checksum mismatch (corrupt serialized state)", fn);
        return FMU_ERROR;
    }
    /* decode into a new snapshot: a refused state leaves *state untouched */
    s = snapshot_for(c, fn, NULL);
    if (!s) return FMU_ERROR;
    memcpy(s, (const unsigned char *)buffer + sizeof h, sizeof *s);
    if (!valid_mode(s->mode)) {
        FMU_LOG_ERROR(c, "%s: corrupt state (mode %d)", fn, (int)s->mode);
        free(s);
        return FMU_ERROR;
    }
    initialized = !(s->mode & (M_INSTANTIATED | M_INIT));
    if (model_validate_state(&s->data, initialized, s->mode == M_STEP_FAILED, fmu_model_logger, c) != MODEL_OK) {
        FMU_LOG_ERROR(c, "%s: invalid state (see the message above)", fn);
        free(s);
        return FMU_ERROR;
    }
    if (*state) {
        memcpy(*state, s, sizeof *s);
        free(s);
    } else {
        *state = s;
    }
    return FMU_OK;
}

/*
 * se3sync plant: the FMI 2.0 Co-Simulation interface around model.c.
 *
 * Every instance owns its data (no global or static mutable data).  Calls that are
 * illegal in the current state, unknown value references, refused values and bad
 * parameters return fmi2Error, log a message through the importer's logger and leave the
 * instance unchanged (except a failed fmi2DoStep, after which the instance is in the
 * "step failed" state: restore an FMU state, reset, terminate or free it).
 */
#include <math.h>
#include <stdarg.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "fmi2Functions.h"
#include "model.h"

typedef enum {
    M_INSTANTIATED = 1 << 0,
    M_INIT = 1 << 1,
    M_STEP_COMPLETE = 1 << 2,
    M_STEP_FAILED = 1 << 3,
    M_TERMINATED = 1 << 4
} Mode;

#define M_ANY (M_INSTANTIATED | M_INIT | M_STEP_COMPLETE | M_STEP_FAILED | M_TERMINATED)

/* log categories (bit flags) */
#define CAT_EVENTS   (1u << 0)
#define CAT_WARNING  (1u << 1)
#define CAT_DISCARD  (1u << 2)
#define CAT_ERROR    (1u << 3)
#define CAT_FATAL    (1u << 4)
#define CAT_CALLS    (1u << 5)
#define CAT_ALL      0x3fu

static const struct {
    const char *name;
    unsigned int flag;
} CATEGORIES[] = {
    {"logEvents", CAT_EVENTS},         {"logStatusWarning", CAT_WARNING}, {"logStatusDiscard", CAT_DISCARD},
    {"logStatusError", CAT_ERROR},     {"logStatusFatal", CAT_FATAL},     {"logCalls", CAT_CALLS},
    {"logAll", CAT_ALL},
};
#define N_CATEGORIES (sizeof CATEGORIES / sizeof CATEGORIES[0])

typedef struct {
    Mode mode;
    ModelData data;
} Snapshot;

typedef struct {
    char *name;
    fmi2CallbackLogger logger;
    fmi2ComponentEnvironment env;
    fmi2Boolean loggingOn;
    unsigned int categories;
    Mode mode;
    double start_time, stop_time;
    int stop_defined;
    Snapshot s; /* everything an FMU state holds; s.mode mirrors mode on get */
} Instance;

#define SERIAL_MAGIC "SE3SYNC\x01"
#define SERIAL_VERSION 1u

typedef struct {
    char magic[8];
    uint32_t version;
    uint32_t n_bodies;
    uint64_t payload;
} SerialHeader;

/* ------------------------------------------------------------------ logging */

static unsigned int category_flag(const char *category)
{
    for (size_t k = 0; k < N_CATEGORIES; k++)
        if (strcmp(category, CATEGORIES[k].name) == 0) return CATEGORIES[k].flag;
    return 0;
}

static void vlog_instance(Instance *c, fmi2Status status, const char *category, const char *fmt, va_list ap)
{
    char buf[1024];
    if (!c || !c->logger) return;
    /* warnings and errors are always reported; other messages only when enabled */
    if (status < fmi2Warning && !(c->loggingOn && (c->categories & category_flag(category)))) return;
    vsnprintf(buf, sizeof buf, fmt, ap);
    for (char *p = buf; *p; p++)
        if (*p == '%') *p = '#'; /* the logger treats the message as a format string */
    c->logger(c->env, c->name, status, category, buf);
}

static void log_instance(Instance *c, fmi2Status status, const char *category, const char *fmt, ...)
{
    va_list ap;
    va_start(ap, fmt);
    vlog_instance(c, status, category, fmt, ap);
    va_end(ap);
}

#define LOG_ERROR(c, ...) log_instance(c, fmi2Error, "logStatusError", __VA_ARGS__)

/* adapter handed to model.c */
static void model_logger(void *env, int status, const char *category, const char *message)
{
    log_instance((Instance *)env, (fmi2Status)status, category, "%s", message);
}

static const char *mode_name(Mode m)
{
    switch (m) {
    case M_INSTANTIATED: return "instantiated";
    case M_INIT: return "initialization mode";
    case M_STEP_COMPLETE: return "step complete";
    case M_STEP_FAILED: return "step failed";
    case M_TERMINATED: return "terminated";
    }
    return "?";
}

/* NULL-instance guard and call-sequence check */
static int allowed(Instance *c, const char *fn, unsigned int modes)
{
    if (!c) return 0;
    if (c->mode & modes) return 1;
    LOG_ERROR(c, "%s: illegal call in state '%s'", fn, mode_name(c->mode));
    return 0;
}

#define CHECK(c, fn, modes)                     \
    do {                                        \
        if (!allowed((c), (fn), (modes))) return fmi2Error; \
    } while (0)

/* ------------------------------------------------------------------ common functions */

const char *fmi2GetTypesPlatform(void) { return fmi2TypesPlatform; }

const char *fmi2GetVersion(void) { return fmi2Version; }

fmi2Status fmi2SetDebugLogging(fmi2Component comp, fmi2Boolean loggingOn, size_t nCategories,
                               const fmi2String categories[])
{
    Instance *c = (Instance *)comp;
    unsigned int mask = 0;
    CHECK(c, "fmi2SetDebugLogging", M_ANY);
    if (nCategories > 0 && !categories) {
        LOG_ERROR(c, "fmi2SetDebugLogging: categories is NULL");
        return fmi2Error;
    }
    for (size_t k = 0; k < nCategories; k++) {
        unsigned int f = categories[k] ? category_flag(categories[k]) : 0;
        if (!f) {
            LOG_ERROR(c, "fmi2SetDebugLogging: unknown log category '%s'", categories[k] ? categories[k] : "(null)");
            return fmi2Error;
        }
        mask |= f;
    }
    c->loggingOn = loggingOn;
    c->categories = nCategories == 0 ? CAT_ALL : mask;
    return fmi2OK;
}

fmi2Component fmi2Instantiate(fmi2String instanceName, fmi2Type fmuType, fmi2String fmuGUID,
                              fmi2String fmuResourceLocation, const fmi2CallbackFunctions *functions,
                              fmi2Boolean visible, fmi2Boolean loggingOn)
{
    fmi2CallbackLogger logger = functions ? functions->logger : NULL;
    fmi2ComponentEnvironment env = functions ? functions->componentEnvironment : NULL;
    const char *name = instanceName ? instanceName : "";
    Instance *c;
    (void)fmuResourceLocation;
    (void)visible;
    if (!instanceName || !instanceName[0]) {
        if (logger) logger(env, name, fmi2Error, "logStatusError", "fmi2Instantiate: missing instance name");
        return NULL;
    }
    if (fmuType != fmi2CoSimulation) {
        if (logger)
            logger(env, name, fmi2Error, "logStatusError",
                   "fmi2Instantiate: this FMU supports Co-Simulation only (fmuType must be fmi2CoSimulation)");
        return NULL;
    }
    if (!fmuGUID || strcmp(fmuGUID, FMU_GUID) != 0) {
        if (logger) {
            char buf[256];
            snprintf(buf, sizeof buf, "fmi2Instantiate: GUID mismatch: got '%.80s', this binary is '%s'",
                     fmuGUID ? fmuGUID : "(null)", FMU_GUID);
            for (char *p = buf; *p; p++)
                if (*p == '%') *p = '#';
            logger(env, name, fmi2Error, "logStatusError", buf);
        }
        return NULL;
    }
    c = (Instance *)calloc(1, sizeof *c);
    if (c) c->name = (char *)malloc(strlen(instanceName) + 1);
    if (!c || !c->name) {
        if (logger) logger(env, name, fmi2Fatal, "logStatusFatal", "fmi2Instantiate: out of memory");
        if (c) free(c);
        return NULL;
    }
    strcpy(c->name, instanceName);
    c->logger = logger;
    c->env = env;
    c->loggingOn = loggingOn;
    c->categories = CAT_ALL;
    c->mode = M_INSTANTIATED;
    model_set_defaults(&c->s.data);
    log_instance(c, fmi2OK, "logEvents", "fmi2Instantiate: %d bodies, GUID %s", N_BODIES, FMU_GUID);
    return c;
}

void fmi2FreeInstance(fmi2Component comp)
{
    Instance *c = (Instance *)comp;
    if (!c) return;
    free(c->name);
    free(c);
}

fmi2Status fmi2SetupExperiment(fmi2Component comp, fmi2Boolean toleranceDefined, fmi2Real tolerance,
                               fmi2Real startTime, fmi2Boolean stopTimeDefined, fmi2Real stopTime)
{
    Instance *c = (Instance *)comp;
    (void)toleranceDefined;
    (void)tolerance;
    CHECK(c, "fmi2SetupExperiment", M_INSTANTIATED);
    if (!isfinite(startTime)) {
        LOG_ERROR(c, "fmi2SetupExperiment: startTime = %g is not finite", startTime);
        return fmi2Error;
    }
    if (stopTimeDefined && !(stopTime >= startTime)) {
        LOG_ERROR(c, "fmi2SetupExperiment: stopTime = %g is before startTime = %g", stopTime, startTime);
        return fmi2Error;
    }
    c->start_time = startTime;
    c->stop_time = stopTime;
    c->stop_defined = stopTimeDefined ? 1 : 0;
    c->s.data.time = startTime;
    return fmi2OK;
}

fmi2Status fmi2EnterInitializationMode(fmi2Component comp)
{
    Instance *c = (Instance *)comp;
    CHECK(c, "fmi2EnterInitializationMode", M_INSTANTIATED);
    c->mode = M_INIT;
    model_preview(&c->s.data);
    return fmi2OK;
}

fmi2Status fmi2ExitInitializationMode(fmi2Component comp)
{
    Instance *c = (Instance *)comp;
    int st;
    CHECK(c, "fmi2ExitInitializationMode", M_INIT);
    st = model_initialize(&c->s.data, model_logger, c);
    if (st == MODEL_ERROR) {
        LOG_ERROR(c, "fmi2ExitInitializationMode: invalid parameters (see the messages above); "
                     "still in initialization mode");
        return fmi2Error;
    }
    c->s.data.time = c->start_time;
    c->mode = M_STEP_COMPLETE;
    return st == MODEL_WARNING ? fmi2Warning : fmi2OK;
}

fmi2Status fmi2Terminate(fmi2Component comp)
{
    Instance *c = (Instance *)comp;
    CHECK(c, "fmi2Terminate", M_STEP_COMPLETE | M_STEP_FAILED);
    c->mode = M_TERMINATED;
    return fmi2OK;
}

fmi2Status fmi2Reset(fmi2Component comp)
{
    Instance *c = (Instance *)comp;
    CHECK(c, "fmi2Reset", M_ANY);
    c->mode = M_INSTANTIATED;
    c->start_time = 0.0;
    c->stop_time = 0.0;
    c->stop_defined = 0;
    model_set_defaults(&c->s.data);
    return fmi2OK;
}

/* ------------------------------------------------------------------ get / set */

#define GET_MODES (M_INSTANTIATED | M_INIT | M_STEP_COMPLETE | M_STEP_FAILED | M_TERMINATED)

fmi2Status fmi2GetReal(fmi2Component comp, const fmi2ValueReference vr[], size_t nvr, fmi2Real value[])
{
    Instance *c = (Instance *)comp;
    ModelData *d;
    CHECK(c, "fmi2GetReal", GET_MODES);
    if (nvr == 0) return fmi2OK;
    if (!vr || !value) {
        LOG_ERROR(c, "fmi2GetReal: NULL vr or value array");
        return fmi2Error;
    }
    d = &c->s.data;
    if (c->mode & (M_INSTANTIATED | M_INIT)) model_preview(d);
    for (size_t k = 0, run; k < nvr; k += run) {
        int kind;
        unsigned int off;
        const double *p = model_lookup_run(d, vr + k, nvr - k, &kind, &run, &off);
        if (!p) {
            LOG_ERROR(c, "fmi2GetReal: unknown value reference %u", (unsigned)vr[k]);
            return fmi2Error;
        }
        if (kind == VAR_OUTPUT && !d->q_valid && off + run > OFF_Q)
            model_update_quaternions(d); /* quaternions are computed on demand */
        memcpy(value + k, p, run * sizeof(double));
    }
    return fmi2OK;
}

fmi2Status fmi2SetReal(fmi2Component comp, const fmi2ValueReference vr[], size_t nvr, const fmi2Real value[])
{
    Instance *c = (Instance *)comp;
    ModelData *d;
    char name[64];
    CHECK(c, "fmi2SetReal", M_INSTANTIATED | M_INIT | M_STEP_COMPLETE);
    if (nvr == 0) return fmi2OK;
    if (!vr || !value) {
        LOG_ERROR(c, "fmi2SetReal: NULL vr or value array");
        return fmi2Error;
    }
    d = &c->s.data;
    /* check everything first: a refused call changes nothing */
    for (size_t k = 0, run; k < nvr; k += run) {
        int kind;
        unsigned int off;
        (void)model_lookup_run(d, vr + k, nvr - k, &kind, &run, &off);
        if (kind == VAR_UNKNOWN) {
            LOG_ERROR(c, "fmi2SetReal: unknown value reference %u", (unsigned)vr[k]);
            return fmi2Error;
        }
        if (kind == VAR_OUTPUT) {
            model_variable_name(vr[k], name, sizeof name);
            LOG_ERROR(c, "fmi2SetReal: %s (value reference %u) is an output and cannot be set", name,
                      (unsigned)vr[k]);
            return fmi2Error;
        }
        if (kind == VAR_PARAMETER && c->mode == M_STEP_COMPLETE) {
            model_variable_name(vr[k], name, sizeof name);
            LOG_ERROR(c, "fmi2SetReal: %s (value reference %u) is a fixed parameter and cannot be set after "
                         "initialization", name, (unsigned)vr[k]);
            return fmi2Error;
        }
        for (size_t j = k; j < k + run; j++) {
            if (!isfinite(value[j])) {
                model_variable_name(vr[j], name, sizeof name);
                LOG_ERROR(c, "fmi2SetReal: %s = %g is not finite (value reference %u)", name, value[j],
                          (unsigned)vr[j]);
                return fmi2Error;
            }
        }
    }
    for (size_t k = 0, run; k < nvr; k += run) {
        int kind;
        unsigned int off;
        double *p = model_lookup_run(d, vr + k, nvr - k, &kind, &run, &off);
        memcpy(p, value + k, run * sizeof(double));
    }
    return fmi2OK;
}

static fmi2Status no_variables(Instance *c, const char *fn, size_t nvr, const fmi2ValueReference vr[])
{
    if (nvr == 0) return fmi2OK;
    LOG_ERROR(c, "%s: unknown value reference %u (this FMU has no variables of this type)", fn,
              vr ? (unsigned)vr[0] : 0u);
    return fmi2Error;
}

fmi2Status fmi2GetInteger(fmi2Component comp, const fmi2ValueReference vr[], size_t nvr, fmi2Integer value[])
{
    Instance *c = (Instance *)comp;
    (void)value;
    CHECK(c, "fmi2GetInteger", GET_MODES);
    return no_variables(c, "fmi2GetInteger", nvr, vr);
}

fmi2Status fmi2GetBoolean(fmi2Component comp, const fmi2ValueReference vr[], size_t nvr, fmi2Boolean value[])
{
    Instance *c = (Instance *)comp;
    (void)value;
    CHECK(c, "fmi2GetBoolean", GET_MODES);
    return no_variables(c, "fmi2GetBoolean", nvr, vr);
}

fmi2Status fmi2GetString(fmi2Component comp, const fmi2ValueReference vr[], size_t nvr, fmi2String value[])
{
    Instance *c = (Instance *)comp;
    (void)value;
    CHECK(c, "fmi2GetString", GET_MODES);
    return no_variables(c, "fmi2GetString", nvr, vr);
}

fmi2Status fmi2SetInteger(fmi2Component comp, const fmi2ValueReference vr[], size_t nvr, const fmi2Integer value[])
{
    Instance *c = (Instance *)comp;
    (void)value;
    CHECK(c, "fmi2SetInteger", M_INSTANTIATED | M_INIT | M_STEP_COMPLETE);
    return no_variables(c, "fmi2SetInteger", nvr, vr);
}

fmi2Status fmi2SetBoolean(fmi2Component comp, const fmi2ValueReference vr[], size_t nvr, const fmi2Boolean value[])
{
    Instance *c = (Instance *)comp;
    (void)value;
    CHECK(c, "fmi2SetBoolean", M_INSTANTIATED | M_INIT | M_STEP_COMPLETE);
    return no_variables(c, "fmi2SetBoolean", nvr, vr);
}

fmi2Status fmi2SetString(fmi2Component comp, const fmi2ValueReference vr[], size_t nvr, const fmi2String value[])
{
    Instance *c = (Instance *)comp;
    (void)value;
    CHECK(c, "fmi2SetString", M_INSTANTIATED | M_INIT | M_STEP_COMPLETE);
    return no_variables(c, "fmi2SetString", nvr, vr);
}

/* ------------------------------------------------------------------ FMU state */

#define STATE_MODES (M_INSTANTIATED | M_INIT | M_STEP_COMPLETE | M_STEP_FAILED | M_TERMINATED)

fmi2Status fmi2GetFMUstate(fmi2Component comp, fmi2FMUstate *FMUstate)
{
    Instance *c = (Instance *)comp;
    Snapshot *s;
    CHECK(c, "fmi2GetFMUstate", STATE_MODES);
    if (!FMUstate) {
        LOG_ERROR(c, "fmi2GetFMUstate: FMUstate is NULL");
        return fmi2Error;
    }
    s = (Snapshot *)*FMUstate;
    if (!s) {
        s = (Snapshot *)malloc(sizeof *s);
        if (!s) {
            LOG_ERROR(c, "fmi2GetFMUstate: out of memory");
            return fmi2Error;
        }
    }
    c->s.mode = c->mode;
    memcpy(s, &c->s, sizeof *s);
    *FMUstate = s;
    return fmi2OK;
}

fmi2Status fmi2SetFMUstate(fmi2Component comp, fmi2FMUstate FMUstate)
{
    Instance *c = (Instance *)comp;
    CHECK(c, "fmi2SetFMUstate", STATE_MODES);
    if (!FMUstate) {
        LOG_ERROR(c, "fmi2SetFMUstate: FMUstate is NULL");
        return fmi2Error;
    }
    memcpy(&c->s, FMUstate, sizeof c->s);
    c->mode = c->s.mode;
    return fmi2OK;
}

fmi2Status fmi2FreeFMUstate(fmi2Component comp, fmi2FMUstate *FMUstate)
{
    Instance *c = (Instance *)comp;
    CHECK(c, "fmi2FreeFMUstate", M_ANY);
    if (!FMUstate) return fmi2OK;
    free(*FMUstate);
    *FMUstate = NULL;
    return fmi2OK;
}

fmi2Status fmi2SerializedFMUstateSize(fmi2Component comp, fmi2FMUstate FMUstate, size_t *size)
{
    Instance *c = (Instance *)comp;
    CHECK(c, "fmi2SerializedFMUstateSize", M_ANY);
    if (!FMUstate || !size) {
        LOG_ERROR(c, "fmi2SerializedFMUstateSize: NULL argument");
        return fmi2Error;
    }
    *size = sizeof(SerialHeader) + sizeof(Snapshot);
    return fmi2OK;
}

fmi2Status fmi2SerializeFMUstate(fmi2Component comp, fmi2FMUstate FMUstate, fmi2Byte serializedState[],
                                 size_t size)
{
    Instance *c = (Instance *)comp;
    SerialHeader h;
    CHECK(c, "fmi2SerializeFMUstate", M_ANY);
    if (!FMUstate || !serializedState) {
        LOG_ERROR(c, "fmi2SerializeFMUstate: NULL argument");
        return fmi2Error;
    }
    if (size < sizeof h + sizeof(Snapshot)) {
        LOG_ERROR(c, "fmi2SerializeFMUstate: buffer of %lu bytes is too small (need %lu)", (unsigned long)size,
                  (unsigned long)(sizeof h + sizeof(Snapshot)));
        return fmi2Error;
    }
    memset(&h, 0, sizeof h);
    memcpy(h.magic, SERIAL_MAGIC, 8);
    h.version = SERIAL_VERSION;
    h.n_bodies = (uint32_t)N_BODIES;
    h.payload = (uint64_t)sizeof(Snapshot);
    memcpy(serializedState, &h, sizeof h);
    memcpy(serializedState + sizeof h, FMUstate, sizeof(Snapshot));
    return fmi2OK;
}

fmi2Status fmi2DeSerializeFMUstate(fmi2Component comp, const fmi2Byte serializedState[], size_t size,
                                   fmi2FMUstate *FMUstate)
{
    Instance *c = (Instance *)comp;
    SerialHeader h;
    Snapshot *s;
    CHECK(c, "fmi2DeSerializeFMUstate", M_ANY);
    if (!serializedState || !FMUstate) {
        LOG_ERROR(c, "fmi2DeSerializeFMUstate: NULL argument");
        return fmi2Error;
    }
    if (size < sizeof h) {
        LOG_ERROR(c, "fmi2DeSerializeFMUstate: %lu bytes is too short for a serialized state", (unsigned long)size);
        return fmi2Error;
    }
    memcpy(&h, serializedState, sizeof h);
    if (memcmp(h.magic, SERIAL_MAGIC, 8) != 0 || h.version != SERIAL_VERSION) {
        LOG_ERROR(c, "fmi2DeSerializeFMUstate: not a serialized se3sync plant state (bad magic or version)");
        return fmi2Error;
    }
    if (h.n_bodies != (uint32_t)N_BODIES || h.payload != (uint64_t)sizeof(Snapshot)) {
        LOG_ERROR(c, "fmi2DeSerializeFMUstate: state of a %u-body FMU, this FMU has %d bodies", (unsigned)h.n_bodies,
                  N_BODIES);
        return fmi2Error;
    }
    if (size != sizeof h + sizeof(Snapshot)) {
        LOG_ERROR(c, "fmi2DeSerializeFMUstate: size %lu does not match the expected %lu bytes (truncated?)",
                  (unsigned long)size, (unsigned long)(sizeof h + sizeof(Snapshot)));
        return fmi2Error;
    }
    s = (Snapshot *)*FMUstate;
    if (!s) {
        s = (Snapshot *)malloc(sizeof *s);
        if (!s) {
            LOG_ERROR(c, "fmi2DeSerializeFMUstate: out of memory");
            return fmi2Error;
        }
    }
    memcpy(s, serializedState + sizeof h, sizeof *s);
    if (!(s->mode & STATE_MODES)) {
        LOG_ERROR(c, "fmi2DeSerializeFMUstate: corrupt state (mode %d)", (int)s->mode);
        if (!*FMUstate) free(s);
        return fmi2Error;
    }
    *FMUstate = s;
    return fmi2OK;
}

fmi2Status fmi2GetDirectionalDerivative(fmi2Component comp, const fmi2ValueReference vUnknown_ref[],
                                        size_t nUnknown, const fmi2ValueReference vKnown_ref[], size_t nKnown,
                                        const fmi2Real dvKnown[], fmi2Real dvUnknown[])
{
    Instance *c = (Instance *)comp;
    (void)vUnknown_ref; (void)nUnknown; (void)vKnown_ref; (void)nKnown; (void)dvKnown; (void)dvUnknown;
    if (!c) return fmi2Error;
    LOG_ERROR(c, "fmi2GetDirectionalDerivative: not supported (providesDirectionalDerivative = false)");
    return fmi2Error;
}

/* ------------------------------------------------------------------ co-simulation */

fmi2Status fmi2SetRealInputDerivatives(fmi2Component comp, const fmi2ValueReference vr[], size_t nvr,
                                       const fmi2Integer order[], const fmi2Real value[])
{
    Instance *c = (Instance *)comp;
    (void)vr; (void)nvr; (void)order; (void)value;
    if (!c) return fmi2Error;
    LOG_ERROR(c, "fmi2SetRealInputDerivatives: not supported (canInterpolateInputs = false)");
    return fmi2Error;
}

fmi2Status fmi2GetRealOutputDerivatives(fmi2Component comp, const fmi2ValueReference vr[], size_t nvr,
                                        const fmi2Integer order[], fmi2Real value[])
{
    Instance *c = (Instance *)comp;
    (void)vr; (void)nvr; (void)order; (void)value;
    if (!c) return fmi2Error;
    LOG_ERROR(c, "fmi2GetRealOutputDerivatives: not supported (maxOutputDerivativeOrder = 0)");
    return fmi2Error;
}

fmi2Status fmi2DoStep(fmi2Component comp, fmi2Real currentCommunicationPoint, fmi2Real communicationStepSize,
                      fmi2Boolean noSetFMUStatePriorToCurrentPoint)
{
    Instance *c = (Instance *)comp;
    (void)noSetFMUStatePriorToCurrentPoint;
    CHECK(c, "fmi2DoStep", M_STEP_COMPLETE);
    if (!isfinite(communicationStepSize) || !(communicationStepSize > 0.0)) {
        LOG_ERROR(c, "fmi2DoStep: communicationStepSize = %g must be finite and > 0", communicationStepSize);
        return fmi2Error;
    }
    if (!isfinite(currentCommunicationPoint)) {
        LOG_ERROR(c, "fmi2DoStep: currentCommunicationPoint = %g is not finite", currentCommunicationPoint);
        return fmi2Error;
    }
    if (model_do_step(&c->s.data, communicationStepSize, model_logger, c) != MODEL_OK) {
        c->mode = M_STEP_FAILED;
        LOG_ERROR(c, "fmi2DoStep: step from t = %g failed", currentCommunicationPoint);
        return fmi2Error;
    }
    c->s.data.time = currentCommunicationPoint + communicationStepSize;
    return fmi2OK;
}

fmi2Status fmi2CancelStep(fmi2Component comp)
{
    Instance *c = (Instance *)comp;
    if (!c) return fmi2Error;
    LOG_ERROR(c, "fmi2CancelStep: no asynchronous step in progress (fmi2DoStep never returns fmi2Pending)");
    return fmi2Error;
}

fmi2Status fmi2GetStatus(fmi2Component comp, const fmi2StatusKind s, fmi2Status *value)
{
    Instance *c = (Instance *)comp;
    (void)value;
    if (!c) return fmi2Error;
    log_instance(c, fmi2Discard, "logStatusDiscard",
                 "fmi2GetStatus: status kind %d is only defined after fmi2DoStep returned fmi2Pending", (int)s);
    return fmi2Discard;
}

fmi2Status fmi2GetRealStatus(fmi2Component comp, const fmi2StatusKind s, fmi2Real *value)
{
    Instance *c = (Instance *)comp;
    if (!c) return fmi2Error;
    if (s == fmi2LastSuccessfulTime && value) {
        *value = c->s.data.time;
        return fmi2OK;
    }
    log_instance(c, fmi2Discard, "logStatusDiscard", "fmi2GetRealStatus: status kind %d not available", (int)s);
    return fmi2Discard;
}

fmi2Status fmi2GetIntegerStatus(fmi2Component comp, const fmi2StatusKind s, fmi2Integer *value)
{
    Instance *c = (Instance *)comp;
    (void)value;
    if (!c) return fmi2Error;
    log_instance(c, fmi2Discard, "logStatusDiscard", "fmi2GetIntegerStatus: status kind %d not available", (int)s);
    return fmi2Discard;
}

fmi2Status fmi2GetBooleanStatus(fmi2Component comp, const fmi2StatusKind s, fmi2Boolean *value)
{
    Instance *c = (Instance *)comp;
    if (!c) return fmi2Error;
    if (s == fmi2Terminated && value) {
        *value = fmi2False; /* the slave never asks to terminate */
        return fmi2OK;
    }
    log_instance(c, fmi2Discard, "logStatusDiscard", "fmi2GetBooleanStatus: status kind %d not available", (int)s);
    return fmi2Discard;
}

fmi2Status fmi2GetStringStatus(fmi2Component comp, const fmi2StatusKind s, fmi2String *value)
{
    Instance *c = (Instance *)comp;
    (void)value;
    if (!c) return fmi2Error;
    log_instance(c, fmi2Discard, "logStatusDiscard", "fmi2GetStringStatus: status kind %d not available", (int)s);
    return fmi2Discard;
}

/* ------------------------------------------------------------------ model exchange (not provided) */
/* This FMU is Co-Simulation only; the Model Exchange functions are not exported. */

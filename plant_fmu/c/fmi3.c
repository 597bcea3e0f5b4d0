/*
 * se3sync plant: the FMI 3.0 Co-Simulation interface around model.c (same equations,
 * integrator and validation as the FMI 2.0 layer in fmi2.c).
 *
 * Every instance owns its data (no global or static mutable data).  Calls that are
 * illegal in the current state, unknown value references, refused values and bad
 * parameters return fmi3Error, log a message through the importer's logger and leave the
 * instance unchanged (except a failed fmi3DoStep, after which the instance is in the
 * "step failed" state: restore an FMU state, reset, terminate or free it).
 *
 * Co-Simulation only, without event mode, early return, intermediate update, clocks or
 * derivatives: the functions of those parts of the API are exported (so the shared
 * library has the full FMI 3.0 symbol set) and return fmi3Error with a logged
 * "not supported" message.  The independent variable `time` has value reference 0.
 */
#include <math.h>
#include <stdarg.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "fmi3Functions.h"
#include "model.h"

#define VR_TIME 0u /* the independent variable (FMI 3.0 requires one) */

typedef enum {
    M_INSTANTIATED = 1 << 0,
    M_INIT = 1 << 1,
    M_STEP_COMPLETE = 1 << 2, /* FMI 3.0 "Step Mode" */
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
    fmi3LogMessageCallback logger;
    fmi3InstanceEnvironment env;
    fmi3Boolean loggingOn;
    unsigned int categories;
    Mode mode;
    double start_time;
    Snapshot s; /* everything an FMU state holds; s.mode mirrors mode on get */
} Instance;

/* same header layout as the FMI 2.0 layer; version 3 marks an FMI 3.0 instance state */
#define SERIAL_MAGIC "SE3SYNC\x01"
#define SERIAL_VERSION 3u

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

static void vlog_instance(Instance *c, fmi3Status status, const char *category, const char *fmt, va_list ap)
{
    char buf[1024];
    if (!c || !c->logger) return;
    /* warnings and errors are always reported; other messages only when enabled */
    if (status < fmi3Warning && !(c->loggingOn && (c->categories & category_flag(category)))) return;
    vsnprintf(buf, sizeof buf, fmt, ap);
    c->logger(c->env, status, category, buf);
}

static void log_instance(Instance *c, fmi3Status status, const char *category, const char *fmt, ...)
{
    va_list ap;
    va_start(ap, fmt);
    vlog_instance(c, status, category, fmt, ap);
    va_end(ap);
}

#define LOG_ERROR(c, ...) log_instance(c, fmi3Error, "logStatusError", __VA_ARGS__)

/* adapter handed to model.c (MODEL_OK/WARNING/ERROR equal fmi3OK/Warning/Error) */
static void model_logger(void *env, int status, const char *category, const char *message)
{
    log_instance((Instance *)env, (fmi3Status)status, category, "%s", message);
}

static const char *mode_name(Mode m)
{
    switch (m) {
    case M_INSTANTIATED: return "instantiated";
    case M_INIT: return "initialization mode";
    case M_STEP_COMPLETE: return "step mode";
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

#define CHECK(c, fn, modes)                                  \
    do {                                                     \
        if (!allowed((c), (fn), (modes))) return fmi3Error;  \
    } while (0)

static fmi3Status unsupported(fmi3Instance instance, const char *fn, const char *why)
{
    Instance *c = (Instance *)instance;
    if (!c) return fmi3Error;
    LOG_ERROR(c, "%s: not supported (%s)", fn, why);
    return fmi3Error;
}

/* ------------------------------------------------------------------ common functions */

const char *fmi3GetVersion(void) { return fmi3Version; }

fmi3Status fmi3SetDebugLogging(fmi3Instance instance, fmi3Boolean loggingOn, size_t nCategories,
                               const fmi3String categories[])
{
    Instance *c = (Instance *)instance;
    unsigned int mask = 0;
    CHECK(c, "fmi3SetDebugLogging", M_ANY);
    if (nCategories > 0 && !categories) {
        LOG_ERROR(c, "fmi3SetDebugLogging: categories is NULL");
        return fmi3Error;
    }
    for (size_t k = 0; k < nCategories; k++) {
        unsigned int f = categories[k] ? category_flag(categories[k]) : 0;
        if (!f) {
            LOG_ERROR(c, "fmi3SetDebugLogging: unknown log category '%s'", categories[k] ? categories[k] : "(null)");
            return fmi3Error;
        }
        mask |= f;
    }
    c->loggingOn = loggingOn;
    c->categories = nCategories == 0 ? CAT_ALL : mask;
    return fmi3OK;
}

static void log_no_instance(fmi3LogMessageCallback logger, fmi3InstanceEnvironment env, fmi3Status status,
                            const char *category, const char *fmt, ...)
{
    char buf[512];
    va_list ap;
    if (!logger) return;
    va_start(ap, fmt);
    vsnprintf(buf, sizeof buf, fmt, ap);
    va_end(ap);
    logger(env, status, category, buf);
}

fmi3Instance fmi3InstantiateCoSimulation(fmi3String instanceName, fmi3String instantiationToken,
                                         fmi3String resourcePath, fmi3Boolean visible, fmi3Boolean loggingOn,
                                         fmi3Boolean eventModeUsed, fmi3Boolean earlyReturnAllowed,
                                         const fmi3ValueReference requiredIntermediateVariables[],
                                         size_t nRequiredIntermediateVariables,
                                         fmi3InstanceEnvironment instanceEnvironment,
                                         fmi3LogMessageCallback logMessage,
                                         fmi3IntermediateUpdateCallback intermediateUpdate)
{
    Instance *c;
    (void)resourcePath;
    (void)visible;
    (void)earlyReturnAllowed; /* the FMU never returns early */
    (void)requiredIntermediateVariables;
    (void)intermediateUpdate; /* providesIntermediateUpdate = false */
    if (!instanceName || !instanceName[0]) {
        log_no_instance(logMessage, instanceEnvironment, fmi3Error, "logStatusError",
                        "fmi3InstantiateCoSimulation: missing instance name");
        return NULL;
    }
    if (!instantiationToken || strcmp(instantiationToken, FMU_GUID) != 0) {
        log_no_instance(logMessage, instanceEnvironment, fmi3Error, "logStatusError",
                        "fmi3InstantiateCoSimulation: instantiationToken mismatch: got '%.80s', this binary is '%s'",
                        instantiationToken ? instantiationToken : "(null)", FMU_GUID);
        return NULL;
    }
    if (eventModeUsed) {
        log_no_instance(logMessage, instanceEnvironment, fmi3Error, "logStatusError",
                        "fmi3InstantiateCoSimulation: eventModeUsed must be false (hasEventMode = false)");
        return NULL;
    }
    if (nRequiredIntermediateVariables > 0) {
        log_no_instance(logMessage, instanceEnvironment, fmi3Error, "logStatusError",
                        "fmi3InstantiateCoSimulation: requiredIntermediateVariables must be empty "
                        "(no variable has intermediateUpdate = true)");
        return NULL;
    }
    c = (Instance *)calloc(1, sizeof *c);
    if (c) c->name = (char *)malloc(strlen(instanceName) + 1);
    if (!c || !c->name) {
        log_no_instance(logMessage, instanceEnvironment, fmi3Fatal, "logStatusFatal",
                        "fmi3InstantiateCoSimulation: out of memory");
        if (c) free(c);
        return NULL;
    }
    strcpy(c->name, instanceName);
    c->logger = logMessage;
    c->env = instanceEnvironment;
    c->loggingOn = loggingOn;
    c->categories = CAT_ALL;
    c->mode = M_INSTANTIATED;
    model_set_defaults(&c->s.data);
    log_instance(c, fmi3OK, "logEvents", "fmi3InstantiateCoSimulation: instance '%s', %d bodies, token %s",
                 c->name, N_BODIES, FMU_GUID);
    return c;
}

fmi3Instance fmi3InstantiateModelExchange(fmi3String instanceName, fmi3String instantiationToken,
                                          fmi3String resourcePath, fmi3Boolean visible, fmi3Boolean loggingOn,
                                          fmi3InstanceEnvironment instanceEnvironment,
                                          fmi3LogMessageCallback logMessage)
{
    (void)instanceName; (void)instantiationToken; (void)resourcePath; (void)visible; (void)loggingOn;
    log_no_instance(logMessage, instanceEnvironment, fmi3Error, "logStatusError",
                    "fmi3InstantiateModelExchange: not supported (this FMU is Co-Simulation only)");
    return NULL;
}

fmi3Instance fmi3InstantiateScheduledExecution(fmi3String instanceName, fmi3String instantiationToken,
                                               fmi3String resourcePath, fmi3Boolean visible, fmi3Boolean loggingOn,
                                               fmi3InstanceEnvironment instanceEnvironment,
                                               fmi3LogMessageCallback logMessage, fmi3ClockUpdateCallback clockUpdate,
                                               fmi3LockPreemptionCallback lockPreemption,
                                               fmi3UnlockPreemptionCallback unlockPreemption)
{
    (void)instanceName; (void)instantiationToken; (void)resourcePath; (void)visible; (void)loggingOn;
    (void)clockUpdate; (void)lockPreemption; (void)unlockPreemption;
    log_no_instance(logMessage, instanceEnvironment, fmi3Error, "logStatusError",
                    "fmi3InstantiateScheduledExecution: not supported (this FMU is Co-Simulation only)");
    return NULL;
}

void fmi3FreeInstance(fmi3Instance instance)
{
    Instance *c = (Instance *)instance;
    if (!c) return;
    free(c->name);
    free(c);
}

fmi3Status fmi3EnterInitializationMode(fmi3Instance instance, fmi3Boolean toleranceDefined, fmi3Float64 tolerance,
                                       fmi3Float64 startTime, fmi3Boolean stopTimeDefined, fmi3Float64 stopTime)
{
    Instance *c = (Instance *)instance;
    (void)toleranceDefined;
    (void)tolerance;
    CHECK(c, "fmi3EnterInitializationMode", M_INSTANTIATED);
    if (!isfinite(startTime)) {
        LOG_ERROR(c, "fmi3EnterInitializationMode: startTime = %g is not finite", startTime);
        return fmi3Error;
    }
    if (stopTimeDefined && !(stopTime >= startTime)) {
        LOG_ERROR(c, "fmi3EnterInitializationMode: stopTime = %g is before startTime = %g", stopTime, startTime);
        return fmi3Error;
    }
    c->start_time = startTime;
    c->s.data.time = startTime;
    c->mode = M_INIT;
    model_preview(&c->s.data);
    return fmi3OK;
}

fmi3Status fmi3ExitInitializationMode(fmi3Instance instance)
{
    Instance *c = (Instance *)instance;
    int st;
    CHECK(c, "fmi3ExitInitializationMode", M_INIT);
    st = model_initialize(&c->s.data, model_logger, c);
    if (st == MODEL_ERROR) {
        LOG_ERROR(c, "fmi3ExitInitializationMode: invalid parameters (see the messages above); "
                     "still in initialization mode");
        return fmi3Error;
    }
    c->s.data.time = c->start_time;
    c->mode = M_STEP_COMPLETE; /* Co-Simulation without event mode: Step Mode */
    return st == MODEL_WARNING ? fmi3Warning : fmi3OK;
}

fmi3Status fmi3EnterEventMode(fmi3Instance instance)
{
    return unsupported(instance, "fmi3EnterEventMode", "hasEventMode = false");
}

fmi3Status fmi3Terminate(fmi3Instance instance)
{
    Instance *c = (Instance *)instance;
    CHECK(c, "fmi3Terminate", M_STEP_COMPLETE | M_STEP_FAILED);
    c->mode = M_TERMINATED;
    return fmi3OK;
}

fmi3Status fmi3Reset(fmi3Instance instance)
{
    Instance *c = (Instance *)instance;
    CHECK(c, "fmi3Reset", M_ANY);
    c->mode = M_INSTANTIATED;
    c->start_time = 0.0;
    model_set_defaults(&c->s.data);
    return fmi3OK;
}

/* ------------------------------------------------------------------ get / set */

#define GET_MODES (M_INSTANTIATED | M_INIT | M_STEP_COMPLETE | M_STEP_FAILED | M_TERMINATED)
#define SET_MODES (M_INSTANTIATED | M_INIT | M_STEP_COMPLETE)

/* nValues must equal nValueReferences (all variables are scalars) */
static int check_counts(Instance *c, const char *fn, size_t nvr, size_t nValues)
{
    if (nValues == nvr) return 1;
    LOG_ERROR(c, "%s: nValues = %lu must equal nValueReferences = %lu (all variables are scalars)", fn,
              (unsigned long)nValues, (unsigned long)nvr);
    return 0;
}

fmi3Status fmi3GetFloat64(fmi3Instance instance, const fmi3ValueReference valueReferences[],
                          size_t nValueReferences, fmi3Float64 values[], size_t nValues)
{
    Instance *c = (Instance *)instance;
    const fmi3ValueReference *vr = valueReferences;
    const size_t nvr = nValueReferences;
    ModelData *d;
    CHECK(c, "fmi3GetFloat64", GET_MODES);
    if (!check_counts(c, "fmi3GetFloat64", nvr, nValues)) return fmi3Error;
    if (nvr == 0) return fmi3OK;
    if (!vr || !values) {
        LOG_ERROR(c, "fmi3GetFloat64: NULL valueReferences or values array");
        return fmi3Error;
    }
    d = &c->s.data;
    if (c->mode & (M_INSTANTIATED | M_INIT)) model_preview(d);
    for (size_t k = 0, run; k < nvr; k += run) {
        int kind;
        unsigned int off;
        const double *p;
        if (vr[k] == VR_TIME) {
            values[k] = d->time;
            run = 1;
            continue;
        }
        p = model_lookup_run(d, vr + k, nvr - k, &kind, &run, &off);
        if (!p) {
            LOG_ERROR(c, "fmi3GetFloat64: unknown value reference %u", (unsigned)vr[k]);
            return fmi3Error;
        }
        if (kind == VAR_OUTPUT && !d->q_valid && off + run > OFF_Q)
            model_update_quaternions(d); /* quaternions are computed on demand */
        memcpy(values + k, p, run * sizeof(double));
    }
    return fmi3OK;
}

fmi3Status fmi3SetFloat64(fmi3Instance instance, const fmi3ValueReference valueReferences[],
                          size_t nValueReferences, const fmi3Float64 values[], size_t nValues)
{
    Instance *c = (Instance *)instance;
    const fmi3ValueReference *vr = valueReferences;
    const size_t nvr = nValueReferences;
    ModelData *d;
    char name[64];
    CHECK(c, "fmi3SetFloat64", SET_MODES);
    if (!check_counts(c, "fmi3SetFloat64", nvr, nValues)) return fmi3Error;
    if (nvr == 0) return fmi3OK;
    if (!vr || !values) {
        LOG_ERROR(c, "fmi3SetFloat64: NULL valueReferences or values array");
        return fmi3Error;
    }
    d = &c->s.data;
    /* check everything first: a refused call changes nothing */
    for (size_t k = 0, run; k < nvr; k += run) {
        int kind;
        unsigned int off;
        if (vr[k] == VR_TIME) {
            LOG_ERROR(c, "fmi3SetFloat64: time (value reference 0) is the independent variable and cannot be set");
            return fmi3Error;
        }
        (void)model_lookup_run(d, vr + k, nvr - k, &kind, &run, &off);
        if (kind == VAR_UNKNOWN) {
            LOG_ERROR(c, "fmi3SetFloat64: unknown value reference %u", (unsigned)vr[k]);
            return fmi3Error;
        }
        if (kind == VAR_OUTPUT) {
            model_variable_name(vr[k], name, sizeof name);
            LOG_ERROR(c, "fmi3SetFloat64: %s (value reference %u) is an output and cannot be set", name,
                      (unsigned)vr[k]);
            return fmi3Error;
        }
        if (kind == VAR_PARAMETER && c->mode == M_STEP_COMPLETE) {
            model_variable_name(vr[k], name, sizeof name);
            LOG_ERROR(c, "fmi3SetFloat64: %s (value reference %u) is a fixed parameter and cannot be set after "
                         "initialization", name, (unsigned)vr[k]);
            return fmi3Error;
        }
        for (size_t j = k; j < k + run; j++) {
            if (!isfinite(values[j])) {
                model_variable_name(vr[j], name, sizeof name);
                LOG_ERROR(c, "fmi3SetFloat64: %s = %g is not finite (value reference %u)", name, values[j],
                          (unsigned)vr[j]);
                return fmi3Error;
            }
        }
    }
    for (size_t k = 0, run; k < nvr; k += run) {
        int kind;
        unsigned int off;
        double *p = model_lookup_run(d, vr + k, nvr - k, &kind, &run, &off);
        memcpy(p, values + k, run * sizeof(double));
    }
    return fmi3OK;
}

static fmi3Status no_variables(Instance *c, const char *fn, size_t nvr, const fmi3ValueReference vr[])
{
    if (nvr == 0) return fmi3OK;
    LOG_ERROR(c, "%s: unknown value reference %u (this FMU has only Float64 variables)", fn,
              vr ? (unsigned)vr[0] : 0u);
    return fmi3Error;
}

#define GET_NONE(T, CT)                                                                                       \
    fmi3Status fmi3Get##T(fmi3Instance instance, const fmi3ValueReference valueReferences[],                  \
                          size_t nValueReferences, CT values[], size_t nValues)                               \
    {                                                                                                         \
        Instance *c = (Instance *)instance;                                                                   \
        (void)values;                                                                                         \
        (void)nValues;                                                                                        \
        CHECK(c, "fmi3Get" #T, GET_MODES);                                                                    \
        return no_variables(c, "fmi3Get" #T, nValueReferences, valueReferences);                              \
    }

#define SET_NONE(T, CT)                                                                                       \
    fmi3Status fmi3Set##T(fmi3Instance instance, const fmi3ValueReference valueReferences[],                  \
                          size_t nValueReferences, const CT values[], size_t nValues)                         \
    {                                                                                                         \
        Instance *c = (Instance *)instance;                                                                   \
        (void)values;                                                                                         \
        (void)nValues;                                                                                        \
        CHECK(c, "fmi3Set" #T, SET_MODES);                                                                    \
        return no_variables(c, "fmi3Set" #T, nValueReferences, valueReferences);                              \
    }

GET_NONE(Float32, fmi3Float32)
GET_NONE(Int8, fmi3Int8)
GET_NONE(UInt8, fmi3UInt8)
GET_NONE(Int16, fmi3Int16)
GET_NONE(UInt16, fmi3UInt16)
GET_NONE(Int32, fmi3Int32)
GET_NONE(UInt32, fmi3UInt32)
GET_NONE(Int64, fmi3Int64)
GET_NONE(UInt64, fmi3UInt64)
GET_NONE(Boolean, fmi3Boolean)
GET_NONE(String, fmi3String)

SET_NONE(Float32, fmi3Float32)
SET_NONE(Int8, fmi3Int8)
SET_NONE(UInt8, fmi3UInt8)
SET_NONE(Int16, fmi3Int16)
SET_NONE(UInt16, fmi3UInt16)
SET_NONE(Int32, fmi3Int32)
SET_NONE(UInt32, fmi3UInt32)
SET_NONE(Int64, fmi3Int64)
SET_NONE(UInt64, fmi3UInt64)
SET_NONE(Boolean, fmi3Boolean)
SET_NONE(String, fmi3String)

fmi3Status fmi3GetBinary(fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences,
                         size_t valueSizes[], fmi3Binary values[], size_t nValues)
{
    Instance *c = (Instance *)instance;
    (void)valueSizes; (void)values; (void)nValues;
    CHECK(c, "fmi3GetBinary", GET_MODES);
    return no_variables(c, "fmi3GetBinary", nValueReferences, valueReferences);
}

fmi3Status fmi3SetBinary(fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences,
                         const size_t valueSizes[], const fmi3Binary values[], size_t nValues)
{
    Instance *c = (Instance *)instance;
    (void)valueSizes; (void)values; (void)nValues;
    CHECK(c, "fmi3SetBinary", SET_MODES);
    return no_variables(c, "fmi3SetBinary", nValueReferences, valueReferences);
}

fmi3Status fmi3GetClock(fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences,
                        fmi3Clock values[])
{
    Instance *c = (Instance *)instance;
    (void)values;
    CHECK(c, "fmi3GetClock", GET_MODES);
    return no_variables(c, "fmi3GetClock", nValueReferences, valueReferences);
}

fmi3Status fmi3SetClock(fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences,
                        const fmi3Clock values[])
{
    Instance *c = (Instance *)instance;
    (void)values;
    CHECK(c, "fmi3SetClock", SET_MODES);
    return no_variables(c, "fmi3SetClock", nValueReferences, valueReferences);
}

/* ------------------------------------------------------------------ variable dependencies */

fmi3Status fmi3GetNumberOfVariableDependencies(fmi3Instance instance, fmi3ValueReference valueReference,
                                               size_t *nDependencies)
{
    (void)valueReference; (void)nDependencies;
    return unsupported(instance, "fmi3GetNumberOfVariableDependencies", "providesPerElementDependencies = false");
}

fmi3Status fmi3GetVariableDependencies(fmi3Instance instance, fmi3ValueReference dependent,
                                       size_t elementIndicesOfDependent[], fmi3ValueReference independents[],
                                       size_t elementIndicesOfIndependents[], fmi3DependencyKind dependencyKinds[],
                                       size_t nDependencies)
{
    (void)dependent; (void)elementIndicesOfDependent; (void)independents; (void)elementIndicesOfIndependents;
    (void)dependencyKinds; (void)nDependencies;
    return unsupported(instance, "fmi3GetVariableDependencies", "providesPerElementDependencies = false");
}

/* ------------------------------------------------------------------ FMU state */

#define STATE_MODES (M_INSTANTIATED | M_INIT | M_STEP_COMPLETE | M_STEP_FAILED | M_TERMINATED)

fmi3Status fmi3GetFMUState(fmi3Instance instance, fmi3FMUState *FMUState)
{
    Instance *c = (Instance *)instance;
    Snapshot *s;
    CHECK(c, "fmi3GetFMUState", STATE_MODES);
    if (!FMUState) {
        LOG_ERROR(c, "fmi3GetFMUState: FMUState is NULL");
        return fmi3Error;
    }
    s = (Snapshot *)*FMUState;
    if (!s) {
        s = (Snapshot *)malloc(sizeof *s);
        if (!s) {
            LOG_ERROR(c, "fmi3GetFMUState: out of memory");
            return fmi3Error;
        }
    }
    c->s.mode = c->mode;
    memcpy(s, &c->s, sizeof *s);
    *FMUState = s;
    return fmi3OK;
}

fmi3Status fmi3SetFMUState(fmi3Instance instance, fmi3FMUState FMUState)
{
    Instance *c = (Instance *)instance;
    CHECK(c, "fmi3SetFMUState", STATE_MODES);
    if (!FMUState) {
        LOG_ERROR(c, "fmi3SetFMUState: FMUState is NULL");
        return fmi3Error;
    }
    memcpy(&c->s, FMUState, sizeof c->s);
    c->mode = c->s.mode;
    return fmi3OK;
}

fmi3Status fmi3FreeFMUState(fmi3Instance instance, fmi3FMUState *FMUState)
{
    Instance *c = (Instance *)instance;
    CHECK(c, "fmi3FreeFMUState", M_ANY);
    if (!FMUState) return fmi3OK;
    free(*FMUState);
    *FMUState = NULL;
    return fmi3OK;
}

fmi3Status fmi3SerializedFMUStateSize(fmi3Instance instance, fmi3FMUState FMUState, size_t *size)
{
    Instance *c = (Instance *)instance;
    CHECK(c, "fmi3SerializedFMUStateSize", M_ANY);
    if (!FMUState || !size) {
        LOG_ERROR(c, "fmi3SerializedFMUStateSize: NULL argument");
        return fmi3Error;
    }
    *size = sizeof(SerialHeader) + sizeof(Snapshot);
    return fmi3OK;
}

fmi3Status fmi3SerializeFMUState(fmi3Instance instance, fmi3FMUState FMUState, fmi3Byte serializedState[],
                                 size_t size)
{
    Instance *c = (Instance *)instance;
    SerialHeader h;
    CHECK(c, "fmi3SerializeFMUState", M_ANY);
    if (!FMUState || !serializedState) {
        LOG_ERROR(c, "fmi3SerializeFMUState: NULL argument");
        return fmi3Error;
    }
    if (size < sizeof h + sizeof(Snapshot)) {
        LOG_ERROR(c, "fmi3SerializeFMUState: buffer of %lu bytes is too small (need %lu)", (unsigned long)size,
                  (unsigned long)(sizeof h + sizeof(Snapshot)));
        return fmi3Error;
    }
    memset(&h, 0, sizeof h);
    memcpy(h.magic, SERIAL_MAGIC, 8);
    h.version = SERIAL_VERSION;
    h.n_bodies = (uint32_t)N_BODIES;
    h.payload = (uint64_t)sizeof(Snapshot);
    memcpy(serializedState, &h, sizeof h);
    memcpy(serializedState + sizeof h, FMUState, sizeof(Snapshot));
    return fmi3OK;
}

fmi3Status fmi3DeserializeFMUState(fmi3Instance instance, const fmi3Byte serializedState[], size_t size,
                                   fmi3FMUState *FMUState)
{
    Instance *c = (Instance *)instance;
    SerialHeader h;
    Snapshot *s;
    CHECK(c, "fmi3DeserializeFMUState", M_ANY);
    if (!serializedState || !FMUState) {
        LOG_ERROR(c, "fmi3DeserializeFMUState: NULL argument");
        return fmi3Error;
    }
    if (size < sizeof h) {
        LOG_ERROR(c, "fmi3DeserializeFMUState: %lu bytes is too short for a serialized state", (unsigned long)size);
        return fmi3Error;
    }
    memcpy(&h, serializedState, sizeof h);
    if (memcmp(h.magic, SERIAL_MAGIC, 8) != 0 || h.version != SERIAL_VERSION) {
        LOG_ERROR(c, "fmi3DeserializeFMUState: not a serialized se3sync plant FMI 3.0 state (bad magic or version)");
        return fmi3Error;
    }
    if (h.n_bodies != (uint32_t)N_BODIES || h.payload != (uint64_t)sizeof(Snapshot)) {
        LOG_ERROR(c, "fmi3DeserializeFMUState: state of a %u-body FMU, this FMU has %d bodies", (unsigned)h.n_bodies,
                  N_BODIES);
        return fmi3Error;
    }
    if (size != sizeof h + sizeof(Snapshot)) {
        LOG_ERROR(c, "fmi3DeserializeFMUState: size %lu does not match the expected %lu bytes (truncated?)",
                  (unsigned long)size, (unsigned long)(sizeof h + sizeof(Snapshot)));
        return fmi3Error;
    }
    s = (Snapshot *)*FMUState;
    if (!s) {
        s = (Snapshot *)malloc(sizeof *s);
        if (!s) {
            LOG_ERROR(c, "fmi3DeserializeFMUState: out of memory");
            return fmi3Error;
        }
    }
    memcpy(s, serializedState + sizeof h, sizeof *s);
    if (!(s->mode & STATE_MODES)) {
        LOG_ERROR(c, "fmi3DeserializeFMUState: corrupt state (mode %d)", (int)s->mode);
        if (!*FMUState) free(s);
        return fmi3Error;
    }
    *FMUState = s;
    return fmi3OK;
}

/* ------------------------------------------------------------------ derivatives (not provided) */

fmi3Status fmi3GetDirectionalDerivative(fmi3Instance instance, const fmi3ValueReference unknowns[], size_t nUnknowns,
                                        const fmi3ValueReference knowns[], size_t nKnowns, const fmi3Float64 seed[],
                                        size_t nSeed, fmi3Float64 sensitivity[], size_t nSensitivity)
{
    (void)unknowns; (void)nUnknowns; (void)knowns; (void)nKnowns; (void)seed; (void)nSeed; (void)sensitivity;
    (void)nSensitivity;
    return unsupported(instance, "fmi3GetDirectionalDerivative", "providesDirectionalDerivatives = false");
}

fmi3Status fmi3GetAdjointDerivative(fmi3Instance instance, const fmi3ValueReference unknowns[], size_t nUnknowns,
                                    const fmi3ValueReference knowns[], size_t nKnowns, const fmi3Float64 seed[],
                                    size_t nSeed, fmi3Float64 sensitivity[], size_t nSensitivity)
{
    (void)unknowns; (void)nUnknowns; (void)knowns; (void)nKnowns; (void)seed; (void)nSeed; (void)sensitivity;
    (void)nSensitivity;
    return unsupported(instance, "fmi3GetAdjointDerivative", "providesAdjointDerivatives = false");
}

/* ------------------------------------------------------------------ configuration mode, clocks (not provided) */

fmi3Status fmi3EnterConfigurationMode(fmi3Instance instance)
{
    return unsupported(instance, "fmi3EnterConfigurationMode", "the FMU has no structural parameters");
}

fmi3Status fmi3ExitConfigurationMode(fmi3Instance instance)
{
    return unsupported(instance, "fmi3ExitConfigurationMode", "the FMU has no structural parameters");
}

#define NO_CLOCKS "the FMU has no clocks"

fmi3Status fmi3GetIntervalDecimal(fmi3Instance instance, const fmi3ValueReference valueReferences[],
                                  size_t nValueReferences, fmi3Float64 intervals[], fmi3IntervalQualifier qualifiers[])
{
    (void)valueReferences; (void)nValueReferences; (void)intervals; (void)qualifiers;
    return unsupported(instance, "fmi3GetIntervalDecimal", NO_CLOCKS);
}

fmi3Status fmi3GetIntervalFraction(fmi3Instance instance, const fmi3ValueReference valueReferences[],
                                   size_t nValueReferences, fmi3UInt64 counters[], fmi3UInt64 resolutions[],
                                   fmi3IntervalQualifier qualifiers[])
{
    (void)valueReferences; (void)nValueReferences; (void)counters; (void)resolutions; (void)qualifiers;
    return unsupported(instance, "fmi3GetIntervalFraction", NO_CLOCKS);
}

fmi3Status fmi3GetShiftDecimal(fmi3Instance instance, const fmi3ValueReference valueReferences[],
                               size_t nValueReferences, fmi3Float64 shifts[])
{
    (void)valueReferences; (void)nValueReferences; (void)shifts;
    return unsupported(instance, "fmi3GetShiftDecimal", NO_CLOCKS);
}

fmi3Status fmi3GetShiftFraction(fmi3Instance instance, const fmi3ValueReference valueReferences[],
                                size_t nValueReferences, fmi3UInt64 counters[], fmi3UInt64 resolutions[])
{
    (void)valueReferences; (void)nValueReferences; (void)counters; (void)resolutions;
    return unsupported(instance, "fmi3GetShiftFraction", NO_CLOCKS);
}

fmi3Status fmi3SetIntervalDecimal(fmi3Instance instance, const fmi3ValueReference valueReferences[],
                                  size_t nValueReferences, const fmi3Float64 intervals[])
{
    (void)valueReferences; (void)nValueReferences; (void)intervals;
    return unsupported(instance, "fmi3SetIntervalDecimal", NO_CLOCKS);
}

fmi3Status fmi3SetIntervalFraction(fmi3Instance instance, const fmi3ValueReference valueReferences[],
                                   size_t nValueReferences, const fmi3UInt64 counters[],
                                   const fmi3UInt64 resolutions[])
{
    (void)valueReferences; (void)nValueReferences; (void)counters; (void)resolutions;
    return unsupported(instance, "fmi3SetIntervalFraction", NO_CLOCKS);
}

fmi3Status fmi3SetShiftDecimal(fmi3Instance instance, const fmi3ValueReference valueReferences[],
                               size_t nValueReferences, const fmi3Float64 shifts[])
{
    (void)valueReferences; (void)nValueReferences; (void)shifts;
    return unsupported(instance, "fmi3SetShiftDecimal", NO_CLOCKS);
}

fmi3Status fmi3SetShiftFraction(fmi3Instance instance, const fmi3ValueReference valueReferences[],
                                size_t nValueReferences, const fmi3UInt64 counters[], const fmi3UInt64 resolutions[])
{
    (void)valueReferences; (void)nValueReferences; (void)counters; (void)resolutions;
    return unsupported(instance, "fmi3SetShiftFraction", NO_CLOCKS);
}

fmi3Status fmi3EvaluateDiscreteStates(fmi3Instance instance)
{
    return unsupported(instance, "fmi3EvaluateDiscreteStates", "providesEvaluateDiscreteStates = false");
}

fmi3Status fmi3UpdateDiscreteStates(fmi3Instance instance, fmi3Boolean *discreteStatesNeedUpdate,
                                    fmi3Boolean *terminateSimulation, fmi3Boolean *nominalsOfContinuousStatesChanged,
                                    fmi3Boolean *valuesOfContinuousStatesChanged, fmi3Boolean *nextEventTimeDefined,
                                    fmi3Float64 *nextEventTime)
{
    (void)discreteStatesNeedUpdate; (void)terminateSimulation; (void)nominalsOfContinuousStatesChanged;
    (void)valuesOfContinuousStatesChanged; (void)nextEventTimeDefined; (void)nextEventTime;
    return unsupported(instance, "fmi3UpdateDiscreteStates", "hasEventMode = false");
}

/* ------------------------------------------------------------------ model exchange (not provided) */

#define CS_ONLY "this FMU is Co-Simulation only"

fmi3Status fmi3EnterContinuousTimeMode(fmi3Instance instance)
{
    return unsupported(instance, "fmi3EnterContinuousTimeMode", CS_ONLY);
}

fmi3Status fmi3CompletedIntegratorStep(fmi3Instance instance, fmi3Boolean noSetFMUStatePriorToCurrentPoint,
                                       fmi3Boolean *enterEventMode, fmi3Boolean *terminateSimulation)
{
    (void)noSetFMUStatePriorToCurrentPoint; (void)enterEventMode; (void)terminateSimulation;
    return unsupported(instance, "fmi3CompletedIntegratorStep", CS_ONLY);
}

fmi3Status fmi3SetTime(fmi3Instance instance, fmi3Float64 time)
{
    (void)time;
    return unsupported(instance, "fmi3SetTime", CS_ONLY);
}

fmi3Status fmi3SetContinuousStates(fmi3Instance instance, const fmi3Float64 continuousStates[],
                                   size_t nContinuousStates)
{
    (void)continuousStates; (void)nContinuousStates;
    return unsupported(instance, "fmi3SetContinuousStates", CS_ONLY);
}

fmi3Status fmi3GetContinuousStateDerivatives(fmi3Instance instance, fmi3Float64 derivatives[],
                                             size_t nContinuousStates)
{
    (void)derivatives; (void)nContinuousStates;
    return unsupported(instance, "fmi3GetContinuousStateDerivatives", CS_ONLY);
}

fmi3Status fmi3GetEventIndicators(fmi3Instance instance, fmi3Float64 eventIndicators[], size_t nEventIndicators)
{
    (void)eventIndicators; (void)nEventIndicators;
    return unsupported(instance, "fmi3GetEventIndicators", CS_ONLY);
}

fmi3Status fmi3GetContinuousStates(fmi3Instance instance, fmi3Float64 continuousStates[], size_t nContinuousStates)
{
    (void)continuousStates; (void)nContinuousStates;
    return unsupported(instance, "fmi3GetContinuousStates", CS_ONLY);
}

fmi3Status fmi3GetNominalsOfContinuousStates(fmi3Instance instance, fmi3Float64 nominals[], size_t nContinuousStates)
{
    (void)nominals; (void)nContinuousStates;
    return unsupported(instance, "fmi3GetNominalsOfContinuousStates", CS_ONLY);
}

fmi3Status fmi3GetNumberOfEventIndicators(fmi3Instance instance, size_t *nEventIndicators)
{
    (void)nEventIndicators;
    return unsupported(instance, "fmi3GetNumberOfEventIndicators", CS_ONLY);
}

fmi3Status fmi3GetNumberOfContinuousStates(fmi3Instance instance, size_t *nContinuousStates)
{
    (void)nContinuousStates;
    return unsupported(instance, "fmi3GetNumberOfContinuousStates", CS_ONLY);
}

/* ------------------------------------------------------------------ co-simulation */

fmi3Status fmi3EnterStepMode(fmi3Instance instance)
{
    /* only used after event mode, which this FMU does not have (after
     * fmi3ExitInitializationMode it is in Step Mode already) */
    return unsupported(instance, "fmi3EnterStepMode", "hasEventMode = false; the FMU enters Step Mode at "
                                                      "fmi3ExitInitializationMode");
}

fmi3Status fmi3GetOutputDerivatives(fmi3Instance instance, const fmi3ValueReference valueReferences[],
                                    size_t nValueReferences, const fmi3Int32 orders[], fmi3Float64 values[],
                                    size_t nValues)
{
    (void)valueReferences; (void)nValueReferences; (void)orders; (void)values; (void)nValues;
    return unsupported(instance, "fmi3GetOutputDerivatives", "maxOutputDerivativeOrder = 0");
}

fmi3Status fmi3DoStep(fmi3Instance instance, fmi3Float64 currentCommunicationPoint, fmi3Float64 communicationStepSize,
                      fmi3Boolean noSetFMUStatePriorToCurrentPoint, fmi3Boolean *eventHandlingNeeded,
                      fmi3Boolean *terminateSimulation, fmi3Boolean *earlyReturn, fmi3Float64 *lastSuccessfulTime)
{
    Instance *c = (Instance *)instance;
    (void)noSetFMUStatePriorToCurrentPoint;
    CHECK(c, "fmi3DoStep", M_STEP_COMPLETE);
    if (eventHandlingNeeded) *eventHandlingNeeded = fmi3False;
    if (terminateSimulation) *terminateSimulation = fmi3False;
    if (earlyReturn) *earlyReturn = fmi3False;
    if (lastSuccessfulTime) *lastSuccessfulTime = c->s.data.time;
    if (!isfinite(communicationStepSize) || !(communicationStepSize > 0.0)) {
        LOG_ERROR(c, "fmi3DoStep: communicationStepSize = %g must be finite and > 0", communicationStepSize);
        return fmi3Error;
    }
    if (!isfinite(currentCommunicationPoint)) {
        LOG_ERROR(c, "fmi3DoStep: currentCommunicationPoint = %g is not finite", currentCommunicationPoint);
        return fmi3Error;
    }
    if (model_do_step(&c->s.data, communicationStepSize, model_logger, c) != MODEL_OK) {
        c->mode = M_STEP_FAILED;
        LOG_ERROR(c, "fmi3DoStep: step from t = %g failed", currentCommunicationPoint);
        return fmi3Error;
    }
    c->s.data.time = currentCommunicationPoint + communicationStepSize;
    if (lastSuccessfulTime) *lastSuccessfulTime = c->s.data.time;
    return fmi3OK;
}

/* ------------------------------------------------------------------ scheduled execution (not provided) */

fmi3Status fmi3ActivateModelPartition(fmi3Instance instance, fmi3ValueReference clockReference,
                                      fmi3Float64 activationTime)
{
    (void)clockReference; (void)activationTime;
    return unsupported(instance, "fmi3ActivateModelPartition", CS_ONLY);
}

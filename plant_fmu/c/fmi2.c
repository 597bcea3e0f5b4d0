/*
 * se3sync plant: the FMI 2.0 Co-Simulation interface around model.c -- a thin adapter over
 * the version-independent code in fmu_common.c (shared with the FMI 3.0 layer fmi3.c).
 *
 * Every instance owns its data (no global or static mutable data).  Calls that are
 * illegal in the current state, unknown value references, refused values and bad
 * parameters return fmi2Error, log a message through the importer's logger and leave the
 * instance unchanged (except a failed fmi2DoStep, after which the instance is in the
 * "step failed" state: restore an FMU state, reset, terminate or free it).
 */
#include <stdio.h>
#include <string.h>

#include "fmi2Functions.h"
#include "fmu_common.c" /* compiled as part of this file: the FMU's sources stay model.c + fmi2.c */

typedef struct {
    FmuInstance base; /* first member: an Instance * is an FmuInstance * */
    fmi2CallbackLogger logger;
    fmi2ComponentEnvironment env;
} Instance;

static fmi2Status status2(FmuStatus s)
{
    switch (s) {
    case FMU_OK: return fmi2OK;
    case FMU_WARNING: return fmi2Warning;
    case FMU_DISCARD: return fmi2Discard;
    case FMU_ERROR: return fmi2Error;
    case FMU_FATAL: return fmi2Fatal;
    }
    return fmi2Error;
}

static void emit2(FmuInstance *fc, FmuStatus status, const char *category, char *message)
{
    Instance *c = (Instance *)fc;
    if (!c->logger) return;
    for (char *p = message; *p; p++)
        if (*p == '%') *p = '#'; /* the logger treats the message as a format string */
    c->logger(c->env, fc->name ? fc->name : "", status2(status), category, message);
}

static const FmuLayer LAYER2 = {
    emit2, "step complete", "FMUstate", "se3sync plant", 1u /* serialized FMI 2.0 state */, 0 /* no time vr */
};

#define CHECK(c, fn, modes)                                    \
    do {                                                       \
        if (!fmu_allowed((c), (fn), (modes))) return fmi2Error; \
    } while (0)

/* ------------------------------------------------------------------ common functions */

const char *fmi2GetTypesPlatform(void) { return fmi2TypesPlatform; }

const char *fmi2GetVersion(void) { return fmi2Version; }

fmi2Status fmi2SetDebugLogging(fmi2Component comp, fmi2Boolean loggingOn, size_t nCategories,
                               const fmi2String categories[])
{
    return status2(fmu_set_debug_logging((FmuInstance *)comp, "fmi2SetDebugLogging", loggingOn, nCategories,
                                         categories));
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
    c = (Instance *)fmu_alloc(sizeof *c, instanceName, &LAYER2, loggingOn);
    if (!c) {
        if (logger) logger(env, name, fmi2Fatal, "logStatusFatal", "fmi2Instantiate: out of memory");
        return NULL;
    }
    c->logger = logger;
    c->env = env;
    fmu_log(&c->base, FMU_OK, "logEvents", "fmi2Instantiate: %d bodies, GUID %s", N_BODIES, FMU_GUID);
    return c;
}

void fmi2FreeInstance(fmi2Component comp) { fmu_free((FmuInstance *)comp, "fmi2FreeInstance"); }

fmi2Status fmi2SetupExperiment(fmi2Component comp, fmi2Boolean toleranceDefined, fmi2Real tolerance,
                               fmi2Real startTime, fmi2Boolean stopTimeDefined, fmi2Real stopTime)
{
    FmuInstance *c = (FmuInstance *)comp;
    (void)toleranceDefined;
    (void)tolerance;
    CHECK(c, "fmi2SetupExperiment", M_INSTANTIATED);
    if (fmu_check_experiment(c, "fmi2SetupExperiment", startTime, stopTimeDefined, stopTime) != FMU_OK)
        return fmi2Error;
    c->start_time = startTime; /* the stop time is not used */
    c->s.data.time = startTime;
    return fmi2OK;
}

fmi2Status fmi2EnterInitializationMode(fmi2Component comp)
{
    FmuInstance *c = (FmuInstance *)comp;
    CHECK(c, "fmi2EnterInitializationMode", M_INSTANTIATED);
    fmu_enter_initialization_mode(c);
    return fmi2OK;
}

fmi2Status fmi2ExitInitializationMode(fmi2Component comp)
{
    return status2(fmu_exit_initialization_mode((FmuInstance *)comp, "fmi2ExitInitializationMode"));
}

fmi2Status fmi2Terminate(fmi2Component comp)
{
    return status2(fmu_terminate((FmuInstance *)comp, "fmi2Terminate"));
}

fmi2Status fmi2Reset(fmi2Component comp)
{
    return status2(fmu_reset((FmuInstance *)comp, "fmi2Reset"));
}

/* ------------------------------------------------------------------ get / set */

fmi2Status fmi2GetReal(fmi2Component comp, const fmi2ValueReference vr[], size_t nvr, fmi2Real value[])
{
    FmuInstance *c = (FmuInstance *)comp;
    CHECK(c, "fmi2GetReal", GET_MODES);
    if (nvr == 0) return fmi2OK;
    if (!vr || !value) {
        FMU_LOG_ERROR(c, "fmi2GetReal: NULL vr or value array");
        return fmi2Error;
    }
    return status2(fmu_get_float64(c, "fmi2GetReal", vr, nvr, value));
}

fmi2Status fmi2SetReal(fmi2Component comp, const fmi2ValueReference vr[], size_t nvr, const fmi2Real value[])
{
    FmuInstance *c = (FmuInstance *)comp;
    CHECK(c, "fmi2SetReal", SET_MODES);
    if (nvr == 0) return fmi2OK;
    if (!vr || !value) {
        FMU_LOG_ERROR(c, "fmi2SetReal: NULL vr or value array");
        return fmi2Error;
    }
    return status2(fmu_set_float64(c, "fmi2SetReal", vr, nvr, value));
}

#define NO_VARIABLES "this FMU has no variables of this type"

#define GET_SET_NONE(F, MODES, CT)                                                                    \
    fmi2Status F(fmi2Component comp, const fmi2ValueReference vr[], size_t nvr, CT value[])           \
    {                                                                                                 \
        FmuInstance *c = (FmuInstance *)comp;                                                         \
        (void)value;                                                                                  \
        CHECK(c, #F, MODES);                                                                          \
        return status2(fmu_no_variables(c, #F, nvr, vr, NO_VARIABLES));                               \
    }

GET_SET_NONE(fmi2GetInteger, GET_MODES, fmi2Integer)
GET_SET_NONE(fmi2GetBoolean, GET_MODES, fmi2Boolean)
GET_SET_NONE(fmi2GetString, GET_MODES, fmi2String)
GET_SET_NONE(fmi2SetInteger, SET_MODES, const fmi2Integer)
GET_SET_NONE(fmi2SetBoolean, SET_MODES, const fmi2Boolean)
GET_SET_NONE(fmi2SetString, SET_MODES, const fmi2String)

/* ------------------------------------------------------------------ FMU state */

fmi2Status fmi2GetFMUstate(fmi2Component comp, fmi2FMUstate *FMUstate)
{
    return status2(fmu_get_state((FmuInstance *)comp, "fmi2GetFMUstate", FMUstate));
}

fmi2Status fmi2SetFMUstate(fmi2Component comp, fmi2FMUstate FMUstate)
{
    return status2(fmu_set_state((FmuInstance *)comp, "fmi2SetFMUstate", FMUstate));
}

fmi2Status fmi2FreeFMUstate(fmi2Component comp, fmi2FMUstate *FMUstate)
{
    return status2(fmu_free_state((FmuInstance *)comp, "fmi2FreeFMUstate", FMUstate));
}

fmi2Status fmi2SerializedFMUstateSize(fmi2Component comp, fmi2FMUstate FMUstate, size_t *size)
{
    return status2(fmu_serialized_state_size((FmuInstance *)comp, "fmi2SerializedFMUstateSize", FMUstate, size));
}

fmi2Status fmi2SerializeFMUstate(fmi2Component comp, fmi2FMUstate FMUstate, fmi2Byte serializedState[],
                                 size_t size)
{
    return status2(fmu_serialize_state((FmuInstance *)comp, "fmi2SerializeFMUstate", FMUstate, serializedState,
                                       size));
}

fmi2Status fmi2DeSerializeFMUstate(fmi2Component comp, const fmi2Byte serializedState[], size_t size,
                                   fmi2FMUstate *FMUstate)
{
    return status2(fmu_deserialize_state((FmuInstance *)comp, "fmi2DeSerializeFMUstate", serializedState, size,
                                         FMUstate));
}

fmi2Status fmi2GetDirectionalDerivative(fmi2Component comp, const fmi2ValueReference vUnknown_ref[],
                                        size_t nUnknown, const fmi2ValueReference vKnown_ref[], size_t nKnown,
                                        const fmi2Real dvKnown[], fmi2Real dvUnknown[])
{
    (void)vUnknown_ref; (void)nUnknown; (void)vKnown_ref; (void)nKnown; (void)dvKnown; (void)dvUnknown;
    return status2(fmu_unsupported((FmuInstance *)comp, "fmi2GetDirectionalDerivative",
                                   "providesDirectionalDerivative = false"));
}

/* ------------------------------------------------------------------ co-simulation */

fmi2Status fmi2SetRealInputDerivatives(fmi2Component comp, const fmi2ValueReference vr[], size_t nvr,
                                       const fmi2Integer order[], const fmi2Real value[])
{
    (void)vr; (void)nvr; (void)order; (void)value;
    return status2(fmu_unsupported((FmuInstance *)comp, "fmi2SetRealInputDerivatives",
                                   "canInterpolateInputs = false"));
}

fmi2Status fmi2GetRealOutputDerivatives(fmi2Component comp, const fmi2ValueReference vr[], size_t nvr,
                                        const fmi2Integer order[], fmi2Real value[])
{
    (void)vr; (void)nvr; (void)order; (void)value;
    return status2(fmu_unsupported((FmuInstance *)comp, "fmi2GetRealOutputDerivatives",
                                   "maxOutputDerivativeOrder = 0"));
}

fmi2Status fmi2DoStep(fmi2Component comp, fmi2Real currentCommunicationPoint, fmi2Real communicationStepSize,
                      fmi2Boolean noSetFMUStatePriorToCurrentPoint)
{
    FmuInstance *c = (FmuInstance *)comp;
    (void)noSetFMUStatePriorToCurrentPoint;
    CHECK(c, "fmi2DoStep", M_STEP_COMPLETE);
    return status2(fmu_do_step(c, "fmi2DoStep", currentCommunicationPoint, communicationStepSize));
}

fmi2Status fmi2CancelStep(fmi2Component comp)
{
    FmuInstance *c = (FmuInstance *)comp;
    if (!fmu_live(c, "fmi2CancelStep")) return fmi2Error;
    FMU_LOG_ERROR(c, "fmi2CancelStep: no asynchronous step in progress (fmi2DoStep never returns fmi2Pending)");
    return fmi2Error;
}

static fmi2Status status_discard(FmuInstance *c, const char *fn, fmi2StatusKind s)
{
    fmu_log(c, FMU_DISCARD, "logStatusDiscard", "%s: status kind %d not available", fn, (int)s);
    return fmi2Discard;
}

fmi2Status fmi2GetStatus(fmi2Component comp, const fmi2StatusKind s, fmi2Status *value)
{
    FmuInstance *c = (FmuInstance *)comp;
    (void)value;
    if (!fmu_live(c, "fmi2GetStatus")) return fmi2Error;
    fmu_log(c, FMU_DISCARD, "logStatusDiscard",
            "fmi2GetStatus: status kind %d is only defined after fmi2DoStep returned fmi2Pending", (int)s);
    return fmi2Discard;
}

fmi2Status fmi2GetRealStatus(fmi2Component comp, const fmi2StatusKind s, fmi2Real *value)
{
    FmuInstance *c = (FmuInstance *)comp;
    if (!fmu_live(c, "fmi2GetRealStatus")) return fmi2Error;
    if (s == fmi2LastSuccessfulTime && value) {
        *value = c->s.data.time;
        return fmi2OK;
    }
    return status_discard(c, "fmi2GetRealStatus", s);
}

fmi2Status fmi2GetIntegerStatus(fmi2Component comp, const fmi2StatusKind s, fmi2Integer *value)
{
    (void)value;
    if (!fmu_live((FmuInstance *)comp, "fmi2GetIntegerStatus")) return fmi2Error;
    return status_discard((FmuInstance *)comp, "fmi2GetIntegerStatus", s);
}

fmi2Status fmi2GetBooleanStatus(fmi2Component comp, const fmi2StatusKind s, fmi2Boolean *value)
{
    if (!fmu_live((FmuInstance *)comp, "fmi2GetBooleanStatus")) return fmi2Error;
    if (s == fmi2Terminated && value) {
        *value = fmi2False; /* the slave never asks to terminate */
        return fmi2OK;
    }
    return status_discard((FmuInstance *)comp, "fmi2GetBooleanStatus", s);
}

fmi2Status fmi2GetStringStatus(fmi2Component comp, const fmi2StatusKind s, fmi2String *value)
{
    (void)value;
    if (!fmu_live((FmuInstance *)comp, "fmi2GetStringStatus")) return fmi2Error;
    return status_discard((FmuInstance *)comp, "fmi2GetStringStatus", s);
}

/* ------------------------------------------------------------------ model exchange (not provided) */
/* This FMU is Co-Simulation only; the Model Exchange functions are not exported. */

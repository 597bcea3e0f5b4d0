/*
 * se3sync plant: the FMI 3.0 Co-Simulation interface around model.c (same equations,
 * integrator and validation as the FMI 2.0 layer in fmi2.c) -- a thin adapter over the
 * version-independent code in fmu_common.c (shared with fmi2.c).
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
#include <stdarg.h>
#include <stdio.h>
#include <string.h>

#include "fmi3Functions.h"
#include "fmu_common.c" /* compiled as part of this file: the FMU's sources stay model.c + fmi3.c */

typedef struct {
    FmuInstance base; /* first member: an Instance * is an FmuInstance * */
    fmi3LogMessageCallback logger;
    fmi3InstanceEnvironment env;
} Instance;

static fmi3Status status3(FmuStatus s)
{
    switch (s) {
    case FMU_OK: return fmi3OK;
    case FMU_WARNING: return fmi3Warning;
    case FMU_DISCARD: return fmi3Discard;
    case FMU_ERROR: return fmi3Error;
    case FMU_FATAL: return fmi3Fatal;
    }
    return fmi3Error;
}

static void emit3(FmuInstance *fc, FmuStatus status, const char *category, char *message)
{
    Instance *c = (Instance *)fc;
    if (c->logger) c->logger(c->env, status3(status), category, message);
}

/* same serialized header as the FMI 2.0 layer; version 3 marks an FMI 3.0 instance state */
static const FmuLayer LAYER3 = {
    emit3, "step mode", "FMUState", "se3sync plant FMI 3.0", 3u, 1 /* vr 0 is time (FMU_VR_TIME) */
};

#define CHECK(c, fn, modes)                                     \
    do {                                                        \
        if (!fmu_allowed((c), (fn), (modes))) return fmi3Error; \
    } while (0)

static fmi3Status unsupported(fmi3Instance instance, const char *fn, const char *why)
{
    return status3(fmu_unsupported((FmuInstance *)instance, fn, why));
}

/* ------------------------------------------------------------------ common functions */

const char *fmi3GetVersion(void) { return fmi3Version; }

fmi3Status fmi3SetDebugLogging(fmi3Instance instance, fmi3Boolean loggingOn, size_t nCategories,
                               const fmi3String categories[])
{
    return status3(fmu_set_debug_logging((FmuInstance *)instance, "fmi3SetDebugLogging", loggingOn, nCategories,
                                         categories));
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
    c = (Instance *)fmu_alloc(sizeof *c, instanceName, &LAYER3, loggingOn);
    if (!c) {
        log_no_instance(logMessage, instanceEnvironment, fmi3Fatal, "logStatusFatal",
                        "fmi3InstantiateCoSimulation: out of memory");
        return NULL;
    }
    c->logger = logMessage;
    c->env = instanceEnvironment;
    fmu_log(&c->base, FMU_OK, "logEvents", "fmi3InstantiateCoSimulation: instance '%s', %d bodies, token %s",
            c->base.name, N_BODIES, FMU_GUID);
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

void fmi3FreeInstance(fmi3Instance instance) { fmu_free((FmuInstance *)instance, "fmi3FreeInstance"); }

fmi3Status fmi3EnterInitializationMode(fmi3Instance instance, fmi3Boolean toleranceDefined, fmi3Float64 tolerance,
                                       fmi3Float64 startTime, fmi3Boolean stopTimeDefined, fmi3Float64 stopTime)
{
    FmuInstance *c = (FmuInstance *)instance;
    (void)toleranceDefined;
    (void)tolerance;
    CHECK(c, "fmi3EnterInitializationMode", M_INSTANTIATED);
    if (fmu_check_experiment(c, "fmi3EnterInitializationMode", startTime, stopTimeDefined, stopTime) != FMU_OK)
        return fmi3Error;
    c->start_time = startTime;
    c->s.data.time = startTime;
    fmu_enter_initialization_mode(c);
    return fmi3OK;
}

fmi3Status fmi3ExitInitializationMode(fmi3Instance instance)
{
    /* Co-Simulation without event mode: goes to Step Mode */
    return status3(fmu_exit_initialization_mode((FmuInstance *)instance, "fmi3ExitInitializationMode"));
}

fmi3Status fmi3EnterEventMode(fmi3Instance instance)
{
    return unsupported(instance, "fmi3EnterEventMode", "hasEventMode = false");
}

fmi3Status fmi3Terminate(fmi3Instance instance)
{
    return status3(fmu_terminate((FmuInstance *)instance, "fmi3Terminate"));
}

fmi3Status fmi3Reset(fmi3Instance instance)
{
    return status3(fmu_reset((FmuInstance *)instance, "fmi3Reset"));
}

/* ------------------------------------------------------------------ get / set */

/* nValues must equal nValueReferences (all variables are scalars) */
static int check_counts(FmuInstance *c, const char *fn, size_t nvr, size_t nValues)
{
    if (nValues == nvr) return 1;
    FMU_LOG_ERROR(c, "%s: nValues = %lu must equal nValueReferences = %lu (all variables are scalars)", fn,
                  (unsigned long)nValues, (unsigned long)nvr);
    return 0;
}

fmi3Status fmi3GetFloat64(fmi3Instance instance, const fmi3ValueReference valueReferences[],
                          size_t nValueReferences, fmi3Float64 values[], size_t nValues)
{
    FmuInstance *c = (FmuInstance *)instance;
    CHECK(c, "fmi3GetFloat64", GET_MODES);
    if (!check_counts(c, "fmi3GetFloat64", nValueReferences, nValues)) return fmi3Error;
    if (nValueReferences == 0) return fmi3OK;
    if (!valueReferences || !values) {
        FMU_LOG_ERROR(c, "fmi3GetFloat64: NULL valueReferences or values array");
        return fmi3Error;
    }
    return status3(fmu_get_float64(c, "fmi3GetFloat64", valueReferences, nValueReferences, values));
}

fmi3Status fmi3SetFloat64(fmi3Instance instance, const fmi3ValueReference valueReferences[],
                          size_t nValueReferences, const fmi3Float64 values[], size_t nValues)
{
    FmuInstance *c = (FmuInstance *)instance;
    CHECK(c, "fmi3SetFloat64", SET_MODES);
    if (!check_counts(c, "fmi3SetFloat64", nValueReferences, nValues)) return fmi3Error;
    if (nValueReferences == 0) return fmi3OK;
    if (!valueReferences || !values) {
        FMU_LOG_ERROR(c, "fmi3SetFloat64: NULL valueReferences or values array");
        return fmi3Error;
    }
    return status3(fmu_set_float64(c, "fmi3SetFloat64", valueReferences, nValueReferences, values));
}

static fmi3Status no_variables(FmuInstance *c, const char *fn, size_t nvr, const fmi3ValueReference vr[])
{
    return status3(fmu_no_variables(c, fn, nvr, vr, "this FMU has only Float64 variables"));
}

#define GET_NONE(T, CT)                                                                                       \
    fmi3Status fmi3Get##T(fmi3Instance instance, const fmi3ValueReference valueReferences[],                  \
                          size_t nValueReferences, CT values[], size_t nValues)                               \
    {                                                                                                         \
        FmuInstance *c = (FmuInstance *)instance;                                                             \
        (void)values;                                                                                         \
        (void)nValues;                                                                                        \
        CHECK(c, "fmi3Get" #T, GET_MODES);                                                                    \
        return no_variables(c, "fmi3Get" #T, nValueReferences, valueReferences);                              \
    }

#define SET_NONE(T, CT)                                                                                       \
    fmi3Status fmi3Set##T(fmi3Instance instance, const fmi3ValueReference valueReferences[],                  \
                          size_t nValueReferences, const CT values[], size_t nValues)                         \
    {                                                                                                         \
        FmuInstance *c = (FmuInstance *)instance;                                                             \
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
    FmuInstance *c = (FmuInstance *)instance;
    (void)valueSizes; (void)values; (void)nValues;
    CHECK(c, "fmi3GetBinary", GET_MODES);
    return no_variables(c, "fmi3GetBinary", nValueReferences, valueReferences);
}

fmi3Status fmi3SetBinary(fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences,
                         const size_t valueSizes[], const fmi3Binary values[], size_t nValues)
{
    FmuInstance *c = (FmuInstance *)instance;
    (void)valueSizes; (void)values; (void)nValues;
    CHECK(c, "fmi3SetBinary", SET_MODES);
    return no_variables(c, "fmi3SetBinary", nValueReferences, valueReferences);
}

fmi3Status fmi3GetClock(fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences,
                        fmi3Clock values[])
{
    FmuInstance *c = (FmuInstance *)instance;
    (void)values;
    CHECK(c, "fmi3GetClock", GET_MODES);
    return no_variables(c, "fmi3GetClock", nValueReferences, valueReferences);
}

fmi3Status fmi3SetClock(fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences,
                        const fmi3Clock values[])
{
    FmuInstance *c = (FmuInstance *)instance;
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

fmi3Status fmi3GetFMUState(fmi3Instance instance, fmi3FMUState *FMUState)
{
    return status3(fmu_get_state((FmuInstance *)instance, "fmi3GetFMUState", FMUState));
}

fmi3Status fmi3SetFMUState(fmi3Instance instance, fmi3FMUState FMUState)
{
    return status3(fmu_set_state((FmuInstance *)instance, "fmi3SetFMUState", FMUState));
}

fmi3Status fmi3FreeFMUState(fmi3Instance instance, fmi3FMUState *FMUState)
{
    return status3(fmu_free_state((FmuInstance *)instance, "fmi3FreeFMUState", FMUState));
}

fmi3Status fmi3SerializedFMUStateSize(fmi3Instance instance, fmi3FMUState FMUState, size_t *size)
{
    return status3(fmu_serialized_state_size((FmuInstance *)instance, "fmi3SerializedFMUStateSize", FMUState, size));
}

fmi3Status fmi3SerializeFMUState(fmi3Instance instance, fmi3FMUState FMUState, fmi3Byte serializedState[],
                                 size_t size)
{
    return status3(fmu_serialize_state((FmuInstance *)instance, "fmi3SerializeFMUState", FMUState, serializedState,
                                       size));
}

fmi3Status fmi3DeserializeFMUState(fmi3Instance instance, const fmi3Byte serializedState[], size_t size,
                                   fmi3FMUState *FMUState)
{
    return status3(fmu_deserialize_state((FmuInstance *)instance, "fmi3DeserializeFMUState", serializedState, size,
                                         FMUState));
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
    FmuInstance *c = (FmuInstance *)instance;
    (void)noSetFMUStatePriorToCurrentPoint;
    CHECK(c, "fmi3DoStep", M_STEP_COMPLETE);
    if (eventHandlingNeeded) *eventHandlingNeeded = fmi3False;
    if (terminateSimulation) *terminateSimulation = fmi3False;
    if (earlyReturn) *earlyReturn = fmi3False;
    if (lastSuccessfulTime) *lastSuccessfulTime = c->s.data.time;
    if (fmu_do_step(c, "fmi3DoStep", currentCommunicationPoint, communicationStepSize) != FMU_OK) return fmi3Error;
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

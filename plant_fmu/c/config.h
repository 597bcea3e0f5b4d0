/* Build configuration of the se3sync plant FMU.  plant_fmu/build.py writes a generated
 * copy of this file (with the number of bodies and the GUID of the FMU) into the FMU's
 * sources/ folder so that the sources compile standalone. */
#ifndef SE3SYNC_CONFIG_H
#define SE3SYNC_CONFIG_H
#ifndef N_BODIES
#define N_BODIES 1
#endif
#ifndef FMU_GUID
#define FMU_GUID "{00000000-0000-0000-0000-000000000000}"
#endif
#endif

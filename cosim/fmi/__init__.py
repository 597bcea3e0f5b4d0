"""The closed loop for FMI tools: the law as a controller FMU (`law_fmu`, pythonfmu), the plant
FMU and the law as an SSP system (`ssp`), and that system run in FMPy and libcosim (`masters`).
pythonfmu is the optional extra ``fmi``; the modules import it where they use it."""

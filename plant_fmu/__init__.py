"""The plant: N rigid bodies on SE(3) as an FMI 2.0 Co-Simulation FMU written in C.

* ``plant_fmu.build``  -- build/cache the .fmu (``fmu_path(n)``, ``build_fmu(n, out)``);
* ``plant_fmu.layout`` -- the value-reference layout (a fixed contract);
* ``plant_fmu.fast``   -- ``FleetFMU``: load it with fmpy and step it with little overhead;
* ``plant_fmu.cli``    -- ``se3sync fmu build``.

See docs/reference/plant-fmu.md.
"""

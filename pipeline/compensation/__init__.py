"""The volumetric compensation: how a spring network is calibrated to follow its material.

A network of springs on a tetrahedral mesh is not the continuum it stands for; its
stress-stretch curve is corrected by virtual tests on a meshed specimen:

* :mod:`.virtual_tensile`: the virtual tensile test of a cylinder specimen;
* :mod:`.loadcases`: the virtual shear test and homogeneous load cases;
* :mod:`.stretch_fit`: the fit of a stretch-dependent correction to several tests at once;
* :mod:`.calibration`: the calibration itself (:func:`~.calibration.compensate`);
* :mod:`.policy`: its defaults and the content-addressed cache of calibrations.
"""

"""What one mobile-mapping campaign shows of the façades: the campaign's points and sensor positions (``campaign``,
``scan``), façade planes (``planes``), the depth grid and its layers (``layers``), occlusion by ray tracing
(``occlusion``), openings and structures (``openings``), all put together per façade in ``observe``.

This package never imports ``lidarmap.map``: an observation knows nothing of the stored map; the map fuses it.
Its data types (``model``: FacadeFrame, Layer, Element, FacadeEvidence, Facade) are what the map stores.
"""

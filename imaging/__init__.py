"""Medical images and structures in, clean geometry out.

* :mod:`imaging.types` : the shared plain data (Grid, Volume, Contour, Roi, StructureSet).
* :mod:`imaging.dicom_io` : CT/MR series -> :class:`~imaging.types.Volume` (``read_series``).
* :mod:`imaging.rtstruct` : RT Structure Set -> :class:`~imaging.types.StructureSet` (``read_rtstruct``).
* :mod:`imaging.meshing` : contours -> masks, volumes (cm³) and watertight meshes (``roi_mask``,
  ``roi_mesh``, ``structure_volume_cc``).
* :mod:`imaging.names` : ROI name synonyms.
* :mod:`imaging.phantom` : the built-in DICOM pelvic phantom (``write_phantom``, ``phantom_spec``).
* :mod:`imaging.inspect` : what a DICOM folder holds (``reachplan inspect``).
* :mod:`imaging.errors` : typed errors and warnings.

Submodules are imported on use; this package imports nothing heavy.
"""

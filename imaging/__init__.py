"""Medical images and structures in, clean geometry out.

* :mod:`reachplan.imaging.types` : the shared plain data (Grid, Volume, Contour, Roi, StructureSet).
* :mod:`reachplan.imaging.dicom_io` : CT/MR series -> :class:`~reachplan.imaging.types.Volume` (``read_series``),
  with :mod:`~reachplan.imaging.dicom_files` (finding and opening files), :mod:`~reachplan.imaging.series_geometry`
  (the frames' grid, ``SeriesTolerance``) and :mod:`~reachplan.imaging.pixels` (decoding pixel data).
* :mod:`reachplan.imaging.rtstruct` : RT Structure Set -> :class:`~reachplan.imaging.types.StructureSet`
  (``read_rtstruct``).
* :mod:`reachplan.imaging.rtplan` : RT Plan (brachy) -> :class:`~reachplan.imaging.brachy_plan.RtPlan` (``read_rtplan``,
  ``channel_paths``); the plan's types live in :mod:`reachplan.imaging.brachy_plan`.
* :mod:`reachplan.imaging.meshing` : contours -> masks, volumes (cm³) and watertight meshes (``roi_mask``,
  ``roi_mesh``, ``structure_volume_cc``).
* :mod:`reachplan.imaging.names` : ROI name synonyms.
* :mod:`reachplan.imaging.phantom` : the pilot phantom and the DICOM writer of built-in cases (``write_phantom``,
  ``phantom_spec``), built from the analytic solids of :mod:`reachplan.imaging.solids`; the files are encoded by
  :mod:`reachplan.imaging.case_dicom`.
* :mod:`reachplan.imaging.clinical` : the built-in clinical case (``clinical_case``, ``write_clinical``), built
  from the smooth solids of :mod:`reachplan.imaging.sweep`; :mod:`reachplan.imaging.anatomy` holds the
  distributions (with their sources) each seed's anatomy is drawn from.
* :mod:`reachplan.imaging.inspect` : what a DICOM folder holds (``reachplan inspect``).
* :mod:`reachplan.imaging.errors` : typed errors and warnings.

Submodules are imported on use; this package imports nothing heavy.
"""

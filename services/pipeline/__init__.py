"""The application layer: one keyword-only use case per job, called by the CLI and the workers (which only
translate to and from it).

- :func:`reconstruct_capture`: a capture to a point cloud.
- :func:`fuse_field`: a cloud plus thermal frames to a field (``thermofield field`` reconstructs first).
- :func:`scan_capture`, :func:`scan_result`: one scan's frames to its stored files, streamed field and job
  result; :func:`process_scan`, :func:`scan_artifacts` the same in memory (:func:`capture_artifacts` before the
  processing, :func:`cloud_artifacts` after the reconstruction, :func:`field_artifacts` after the fusion).
- :func:`inspect_part`, :func:`inspection_artifacts`: a field and a part (type) to the report, deviation clouds and
  verdict (``thermofield inspect`` and the scan job).
- :func:`calibrate_camera_views`, :func:`calibrate_projector_captures`, :func:`place_device`: calibration.
- :func:`register_pair`, :func:`register_scan`: infrared-to-visible registration.
- :func:`field_summary`: what the scan endpoint and MQTT report of a field.
- :class:`TriangulationTables`: the per-calibration precomputation, in memory and on disk.
- :mod:`services.pipeline.jobs`: the service's jobs as the workers run them (:func:`scan_job`,
  :func:`reconstruct_job`, :func:`fuse_job`, :func:`register_job`, :func:`calibrate_job`): each reads and writes
  its job's rows through ``services/db`` and its files in the store.

Import the submodules (``services.pipeline.scan``...): this package does not import them itself, so that
a command pays only for what it uses.
"""

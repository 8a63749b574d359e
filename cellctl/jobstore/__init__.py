"""The job store: what the cell keeps of its jobs on disk, one directory per job under
``<data_dir>/jobs/<job_id>/``.

:mod:`~cellctl.jobstore.jobs` (the job records, ``job.json``, and :class:`~cellctl.jobstore.jobs.JobStore`),
:mod:`~cellctl.jobstore.records` (a job directory's JSON read within bounds),
:mod:`~cellctl.jobstore.history` (the plate history the HMI and the report read, SQLite) and
:mod:`~cellctl.jobstore.rawstore` (the raw acquisition files of ``raw/``, disk first, CRC-checked
chunks). The daemon writes it, the HMI, the report and the offline commands read it; it imports
nothing of them.
"""

"""The analysis worker (`cellctl worker`): receives clouds over Zenoh, analyses, publishes reports.

Shape of one worker process:

* the main process holds the Zenoh session and an asyncio loop: a liveliness token
  (``Keys.worker_alive``), a subscriber for jobs addressed to it (``Keys.worker_job``), one for
  cancellations, an info queryable, heartbeats while a job runs;
* the analysis runs in a *spawned* child process (:class:`~cellctl.worker.process.AnalysisProcess`), so neither Zenoh
  callbacks nor heartbeats wait for it, and a crash or a cancellation kills only the child. The
  child is spawned, never forked: Zenoh's threads must not be forked.

The analysis callable is resolved from a dotted path ``"package.module:function"`` (default
``analysis.pipeline:analyse_job``) and called in the child as
``fn(cloud: ScanCloud, job: AnalysisJob) -> Report | dict``: ``cloud`` is the decoded cloud as
:class:`analysis.cloud_io.ScanCloud` (``xyz_mm`` (n, 3) mm, and when sent the organisation
``pass_id``, ``profile_index``, ``point_index`` and the times ``t_s``), ``job`` is the JobSpec's
:class:`~analysis.contracts.job.AnalysisJob` (validated again in the child: ids, design, the trigger's
placement, settings, ``out_dir``). What it returns is validated as a :class:`~analysis.contracts.job.Report`
before it leaves the child (numpy scalars and arrays are converted); a report that does not fit
the schema is an analysis error.

The modules: :mod:`~cellctl.worker.settings` (WorkerSettings, the BLAS threads),
:mod:`~cellctl.worker.child` (the analysis child's side of the pipe and the messages on it),
:mod:`~cellctl.worker.process` (AnalysisProcess, the worker's side), :mod:`~cellctl.worker.service`
(the Zenoh service, ``run_worker``), :mod:`~cellctl.worker.heap` (the child's heap policy).
"""

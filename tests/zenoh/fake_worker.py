"""A worker spoken by the test itself over Zenoh (the protocol of cellctl.worker.service, by hand): its
announcement, its token, its job subscriber, and its signed events, reports and result chunks.
For cases a real `cellctl worker` cannot play: a lost chunk, a report it should not send, an
announcement of another version."""

from __future__ import annotations

import asyncio
import hashlib
import json
from collections.abc import Callable
from typing import Any

import zenoh

from cellctl.api import API_VERSION, STREAM_FORMAT, JobEvent, JobSpec, Keys, ReportEnvelope
from cellctl.api.proof import chunk_mac, sign
from cellctl.api.transfer import ResultChunk


class FakeWorker:
    """Declares ``worker_id``'s entities on ``session``; ``on_job(spec)`` runs on the loop for each offer.
    ``announce``: the WorkerAnnouncement's fields that differ (an old worker: ``api_version=1``)."""

    def __init__(
        self,
        session: zenoh.Session,
        keys: Keys,
        worker_id: str,
        on_job: Callable[[JobSpec], None] | None = None,
        **announce: Any,
    ) -> None:
        self.session, self.keys, self.worker_id = session, keys, worker_id
        self.specs: list[JobSpec] = []
        loop = asyncio.get_running_loop()
        ann = {"worker_id": worker_id, "host": "test", "pid": 1, "api_version": API_VERSION,
               "stream_format": STREAM_FORMAT, "analysis": "fake", "started_utc": "", **announce}  # fmt: skip
        ann = {k: v for k, v in ann.items() if v is not None}  # None: a field it does not know
        self._announcement = json.dumps(ann).encode()

        def job(sample: zenoh.Sample) -> None:
            spec = JobSpec.model_validate_json(sample.attachment.to_bytes())
            self.specs.append(spec)
            if on_job is not None:
                loop.call_soon_threadsafe(on_job, spec)

        def info(query: zenoh.Query) -> None:
            query.reply(keys.worker_info(worker_id), self._announcement)

        self._ents = [
            session.declare_subscriber(keys.worker_job(worker_id), job),
            session.declare_queryable(keys.worker_info(worker_id), info),
            session.liveliness().declare_token(keys.worker_alive(worker_id)),
        ]

    def event(self, spec: JobSpec, event: str, *, signed: bool = True) -> None:
        ev = JobEvent(job_id=spec.job_id, worker_id=self.worker_id, attempt=spec.attempt, event=event,
                      offer_id=spec.offer_id).to_json()  # fmt: skip
        self.session.put(
            self.keys.job_event(spec.job_id), ev, attachment=sign(spec.offer_key, ev) if signed else None
        )

    def chunks(self, spec: JobSpec, chunks: list[bytes], skip: tuple[int, ...] = ()) -> None:
        for i, data in enumerate(chunks):
            if i in skip:
                continue
            sha = hashlib.sha256(data).hexdigest()
            head = ResultChunk(job_id=spec.job_id, worker_id=self.worker_id, attempt=spec.attempt, index=i,
                               chunks=len(chunks), sha256=sha,
                               mac=chunk_mac(spec.offer_key, spec.job_id, spec.attempt, i, len(chunks), sha))  # fmt: skip
            self.session.put(self.keys.result_chunk(spec.job_id, spec.attempt, i), data,
                             attachment=head.to_json(), congestion_control=zenoh.CongestionControl.BLOCK)  # fmt: skip

    def report(self, spec: JobSpec, **fields: Any) -> None:
        env = ReportEnvelope(job_id=spec.job_id, worker_id=self.worker_id, attempt=spec.attempt,
                             offer_id=spec.offer_id, **{"plate_id": spec.plate_id, "ok": True, **fields})  # fmt: skip
        body = env.to_json()
        self.session.put(self.keys.report(spec.job_id), body, attachment=sign(spec.offer_key, body))

    def close(self) -> None:
        for ent in reversed(self._ents):
            ent.undeclare()

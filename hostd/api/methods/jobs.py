"""job.*: start, pause, resume and cancel a job; its record, its history, its recovery."""

from __future__ import annotations

from typing import TYPE_CHECKING, Annotated, Any

from pydantic import Field, model_validator

from hostd.api.files import check_name
from hostd.api.methods.params import Id, JobFile, MachineId, MachineParams, Params
from hostd.api.rpc import Methods, RpcError
from hostd.machine.jobstart import prepare_start
from hostd.machine.resumes import plan_for, recovery_for

if TYPE_CHECKING:
    from hostd.api.methods.base import Api


class JobStartParams(MachineParams):
    file: JobFile
    start_line: Id = 1
    # From start_line > 1: restore the modal state and approach safely first (false: the
    # raw skip, dangerous: docs/api.md). `force` runs a program that leaves the travel.
    restore: Annotated[bool, Field(strict=True)] = True
    force: Annotated[bool, Field(strict=True)] = False


class JobParams(Params):
    job: Id


class JobRecoveryParams(Params):
    """`job`: where that job should resume. Or `machine`, `file` and `line`: the plan
    job.start would send to resume that file at that line (what `hostd run --from` shows)."""

    job: Id | None = None
    machine: MachineId | None = None
    file: str | None = None
    line: Id | None = None

    @model_validator(mode="after")
    def _one_form(self) -> JobRecoveryParams:
        plan = (self.machine, self.file, self.line)
        if (self.job is None) == (None in plan) or (self.job is not None and plan != (None,) * 3):
            raise ValueError("give job, or machine, file and line")
        if self.file is not None:
            check_name(self.file)
        return self


class JobListParams(Params):
    machine: MachineId | None = None
    limit: Annotated[int, Field(strict=True, ge=1, le=1000)] = 50


class JobMethods:
    def __init__(self, api: Api) -> None:
        self.api = api

    async def job_start(self, p: JobStartParams) -> dict[str, Any]:
        machine = self.api.machine(p.machine)
        path = await self.api.resolve(p.file)
        warnings: list[str] = []
        start = await prepare_start(
            machine,
            path,
            p.start_line,
            restore=p.restore,
            force=p.force,
            pool=self.api.daemon.workers,
            notes=warnings,
        )
        job = await machine.start_make(
            p.file,
            p.start_line,
            start.preamble,
            counted=start.lines,
            version=start.version,
            sha256=start.sha256,
        )
        answer: dict[str, Any] = {"job": job.id, "preamble": start.preamble}
        if warnings:  # what the job does that the file does not say (M6s ignored)
            answer["warnings"] = warnings
        return answer

    async def job_recovery(self, p: JobRecoveryParams) -> dict[str, Any]:
        pool = self.api.daemon.workers
        if p.job is None:
            assert p.machine is not None and p.file is not None and p.line is not None
            machine = self.api.machine(p.machine)
            path = await self.api.resolve(p.file)
            plan = await plan_for(machine, path, p.line, pool=pool)
            return {**plan.to_json(), "machine": p.machine, "file": p.file}
        job = await (await self.api.store()).get(p.job)
        if job is None:
            raise RpcError(1004, f"no job {p.job}")
        machine = self.api.machine(job.machine)
        path = self.api.jobs.path / (job.file or "")
        plan, about = await recovery_for(machine, path, job, pool=pool)
        result = plan.to_json()
        result.update(
            job=job.id,
            machine=job.machine,
            file=job.file,
            line_executed=job.line_executed,
            lines_acked=job.lines_acked,
            uncertain=about + plan.uncertain,
        )
        return result

    async def job_pause(self, p: MachineParams) -> dict[str, Any]:
        return self.api.machine(p.machine).pause().model_dump(mode="json")

    async def job_resume(self, p: MachineParams) -> dict[str, Any]:
        return self.api.machine(p.machine).resume().model_dump(mode="json")

    async def job_tool_change_done(self, p: MachineParams) -> dict[str, Any]:
        """The operator changed the tool the job waits for: it goes on (1003 if none)."""
        job = await self.api.machine(p.machine).tool_change_done()
        return job.model_dump(mode="json")

    async def job_cancel(self, p: MachineParams) -> dict[str, Any]:
        job = await self.api.machine(p.machine).cancel()
        return job.model_dump(mode="json")

    async def job_get(self, p: JobParams) -> dict[str, Any]:
        for machine in self.api.daemon.machines.values():
            current = machine.current_job()
            if current is not None and current.id == p.job:
                return current.model_dump(mode="json")
        job = await (await self.api.store()).get(p.job)
        if job is None:
            raise RpcError(1004, f"no job {p.job}")
        return dict(job.model_dump(mode="json"))

    async def job_list(self, p: JobListParams) -> list[dict[str, Any]]:
        if p.machine is not None:
            self.api.machine(p.machine)
        jobs = await (await self.api.store()).list_jobs(p.machine, p.limit)
        live = {
            job.id: job
            for m in self.api.daemon.machines.values()
            if (job := m.current_job()) is not None
        }
        return [live.get(j.id, j).model_dump(mode="json") for j in jobs]


def register(m: Methods, api: Api) -> None:
    h = JobMethods(api)
    m.register("job.start", JobStartParams, h.job_start)
    m.register("job.pause", MachineParams, h.job_pause)
    m.register("job.resume", MachineParams, h.job_resume)
    m.register("job.cancel", MachineParams, h.job_cancel)
    m.register("job.tool_change_done", MachineParams, h.job_tool_change_done)
    m.register("job.get", JobParams, h.job_get)
    m.register("job.list", JobListParams, h.job_list)
    m.register("job.recovery", JobRecoveryParams, h.job_recovery)

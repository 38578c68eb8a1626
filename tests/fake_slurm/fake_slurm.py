"""A stand-in for SLURM's sbatch, srun and sinfo, and a queue runner, for testing the cluster scripts.

``sbatch`` checks its options as SLURM would (unknown options, malformed
``--time``/``--mem``/``--array``/``--dependency`` and a ``--cpus-per-task``
above the node's cores are refused), stores the job in the spool directory
``$FAKE_SLURM_DIR`` and prints its id. ``run`` (``python fake_slurm.py run``)
is the scheduler: it runs pending jobs whose dependencies are over, one at a
time, each array task with the ``SLURM_*`` variables a real job sees, in the
directory it was submitted from, with its output in ``--output`` (``%j``,
``%A``, ``%a`` expanded) and killed at its ``--time``; it returns when the
queue is empty. Jobs submitted by running jobs join the queue.

Failure injection: ``FAKE_SLURM_KILL=3,5`` kills (SIGKILL) the 3rd and 5th
array task the runner starts, 0.2 s after their start, as a lost
node would.

``srun [options] COMMAND...`` runs COMMAND; ``sinfo -h -o FORMAT`` knows
``%c`` (``$FAKE_SLURM_CPUS`` or this machine's cores), ``%l``
(``$FAKE_SLURM_TIMELIMIT`` or ``infinite``) and ``%P`` (``debug*``).
Every submission is appended as one JSON line to ``$FAKE_SLURM_DIR/submitted.jsonl``.
"""

from __future__ import annotations

import fcntl
import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

VALUE_OPTIONS = {
    "-a": "array", "--array": "array",
    "-d": "dependency", "--dependency": "dependency",
    "-o": "output", "--output": "output",
    "-c": "cpus-per-task", "--cpus-per-task": "cpus-per-task",
    "-n": "ntasks", "--ntasks": "ntasks",
    "-t": "time", "--time": "time",
    "--mem": "mem",
    "-p": "partition", "--partition": "partition",
    "-A": "account", "--account": "account",
    "-J": "job-name", "--job-name": "job-name",
    "-q": "qos", "--qos": "qos",
}
FLAG_OPTIONS = {"--parsable": "parsable"}
TIME = re.compile(r"^(\d+-)?\d+(:\d+){0,2}$")
MEM = re.compile(r"^\d+[KMGT]?$")
ARRAY = re.compile(r"^\d+(-\d+)?(,\d+(-\d+)?)*(%\d+)?$")
DEPENDENCY = re.compile(r"^(afterany|afterok|afternotok):\d+(:\d+)*$")


def fail(message: str) -> None:
    print(f"sbatch: error: {message}", file=sys.stderr)
    sys.exit(1)


def spool() -> Path:
    path = Path(os.environ["FAKE_SLURM_DIR"])
    path.mkdir(parents=True, exist_ok=True)
    return path


def cores() -> int:
    return int(os.environ.get("FAKE_SLURM_CPUS", os.cpu_count() or 1))


def parse_options(args: list[str]) -> tuple[dict[str, str], list[str]]:
    options: dict[str, str] = {}
    i = 0
    while i < len(args) and args[i].startswith("-"):
        name, sep, value = args[i].partition("=")
        if name in FLAG_OPTIONS and not sep:
            options[FLAG_OPTIONS[name]] = "1"
            i += 1
            continue
        if name not in VALUE_OPTIONS:
            fail(f"unrecognized option '{args[i]}'")
        if not sep:
            i += 1
            if i >= len(args):
                fail(f"option '{name}' requires an argument")
            value = args[i]
        options[VALUE_OPTIONS[name]] = value
        i += 1
    return options, args[i:]


def check(options: dict[str, str]) -> None:
    if "time" in options and not TIME.match(options["time"]):
        fail(f"Invalid time limit specification '{options['time']}'")
    if "mem" in options and not MEM.match(options["mem"]):
        fail(f"Invalid --mem specification '{options['mem']}'")
    if "array" in options and not ARRAY.match(options["array"]):
        fail(f"Invalid job array specification '{options['array']}'")
    if "dependency" in options and not DEPENDENCY.match(options["dependency"]):
        fail(f"Invalid dependency specification '{options['dependency']}'")
    cpus = int(options.get("cpus-per-task", 1))
    if not 1 <= cpus <= cores():
        # Real SLURM would wait forever ("Requested partition configuration not available now").
        fail(f"--cpus-per-task={cpus}: no node has that many cores ({cores()})")


def time_seconds(text: str) -> float:
    days, _, rest = text.rpartition("-")
    parts = [int(p) for p in rest.split(":")]
    if days:
        parts += [0] * (3 - len(parts))
        hours, minutes, seconds = parts
    else:
        hours, minutes, seconds = {1: [0, parts[0], 0], 2: [0] + parts, 3: parts}[len(parts)]
    return ((int(days or 0) * 24 + hours) * 60 + minutes) * 60 + seconds


def array_tasks(spec: str) -> list[int]:
    tasks: list[int] = []
    for part in spec.split("%")[0].split(","):
        first, _, last = part.partition("-")
        tasks.extend(range(int(first), int(last or first) + 1))
    return tasks


def next_id(directory: Path) -> int:
    with open(directory / "counter", "a+") as handle:
        fcntl.flock(handle, fcntl.LOCK_EX)
        handle.seek(0)
        job_id = int(handle.read() or 100) + 1
        handle.seek(0)
        handle.truncate()
        handle.write(str(job_id))
    return job_id


def sbatch(args: list[str]) -> None:
    options, rest = parse_options(args)
    check(options)
    script = Path(rest[0]).read_text() if rest else sys.stdin.read()
    if not script.startswith("#!"):
        fail("This does not look like a batch script.  The first line must start with #!")
    directory = spool()
    job_id = next_id(directory)
    job = {
        "id": job_id,
        "options": options,
        "script": script,
        "cwd": os.getcwd(),
        "env": dict(os.environ),
        "state": "PENDING",
    }
    (directory / f"job-{job_id}.json").write_text(json.dumps(job))
    with open(directory / "submitted.jsonl", "a") as log:
        log.write(json.dumps({"id": job_id, "options": options}) + "\n")
    print(job_id if "parsable" in options else f"Submitted batch job {job_id}")


def load_jobs(directory: Path) -> dict[int, dict]:
    return {int(p.stem.split("-")[1]): json.loads(p.read_text()) for p in directory.glob("job-*.json")}


def is_runnable(job: dict, jobs: dict[int, dict]) -> bool | None:
    """True if the dependencies are met, False if not yet, None if they never will be."""
    spec = job["options"].get("dependency")
    if not spec:
        return True
    kind, *ids = spec.split(":")
    states = [jobs[int(i)]["state"] if int(i) in jobs else "COMPLETED" for i in ids]
    if any(state == "PENDING" for state in states):
        return False
    if kind == "afterok" and any(state != "COMPLETED" for state in states):
        return None
    if kind == "afternotok" and all(state == "COMPLETED" for state in states):
        return None
    return True


def run_task(job: dict, task: int | None, started: int) -> bool:
    options = job["options"]
    job_id = job["id"]
    env = dict(job["env"])
    env.update(
        SLURM_JOB_ID=str(job_id if task is None else job_id * 1000 + task),
        SLURM_SUBMIT_DIR=job["cwd"],
        SLURM_JOB_NAME=options.get("job-name", "sbatch"),
        SLURM_CPUS_PER_TASK=options.get("cpus-per-task", "1"),
        SLURM_NTASKS=options.get("ntasks", "1"),
    )
    name = options.get("output", "slurm-%A_%a.out" if task is not None else "slurm-%j.out")
    name = name.replace("%j", env["SLURM_JOB_ID"]).replace("%A", str(job_id))
    if task is not None:
        env.update(SLURM_ARRAY_JOB_ID=str(job_id), SLURM_ARRAY_TASK_ID=str(task),
                   SLURM_ARRAY_TASK_COUNT=str(len(array_tasks(options["array"]))))
        name = name.replace("%a", str(task))
    script = spool() / f"script-{job_id}"
    script.write_text(job["script"])
    limit = time_seconds(options["time"]) if "time" in options else None
    kill = {int(n) for n in os.environ.get("FAKE_SLURM_KILL", "").split(",") if n}
    output = Path(job["cwd"], name)
    output.parent.mkdir(parents=True, exist_ok=True)
    with open(output, "w") as log:
        process = subprocess.Popen(["bash", str(script)], cwd=job["cwd"], env=env, stdout=log,
                                   stderr=subprocess.STDOUT, start_new_session=True)
        try:
            if task is not None and started in kill:
                time.sleep(0.2)
                os.killpg(process.pid, signal.SIGKILL)
                process.wait()
                log.write("fake_slurm: task killed (node lost)\n")
                return False
            process.wait(timeout=limit)
        except subprocess.TimeoutExpired:
            os.killpg(process.pid, signal.SIGTERM)
            process.wait()
            log.write("fake_slurm: CANCELLED DUE TO TIME LIMIT\n")
            return False
    return process.returncode == 0


def run_queue() -> None:
    directory = spool()
    started = 0
    while True:
        jobs = load_jobs(directory)
        pending = sorted(i for i, job in jobs.items() if job["state"] == "PENDING")
        if not pending:
            return
        for job_id in pending:
            job = jobs[job_id]
            runnable = is_runnable(job, jobs)
            if runnable is None:
                job["state"] = "CANCELLED"
                break
            if runnable:
                tasks = array_tasks(job["options"]["array"]) if "array" in job["options"] else [None]
                ok = True
                for task in tasks:
                    started += task is not None
                    ok = run_task(job, task, started) and ok
                job["state"] = "COMPLETED" if ok else "FAILED"
                break
        else:
            sys.exit(f"fake_slurm: jobs {pending} wait for each other or for jobs that do not exist")
        (directory / f"job-{job_id}.json").write_text(json.dumps(job))


def srun(args: list[str]) -> None:
    i = 0
    while i < len(args) and args[i].startswith("-"):
        i += 1 if "=" in args[i] or args[i] in FLAG_OPTIONS else 2
    os.execvp(args[i], args[i:])


def sinfo(args: list[str]) -> None:
    fmt = "%P %l %c"
    for i, arg in enumerate(args):
        if arg == "-o":
            fmt = args[i + 1]
        elif arg.startswith("--format="):
            fmt = arg.split("=", 1)[1]
    limit = os.environ.get("FAKE_SLURM_TIMELIMIT", "infinite")
    print(fmt.replace("%c", str(cores())).replace("%l", limit).replace("%P", "debug*"))


if __name__ == "__main__":
    command, arguments = sys.argv[1], sys.argv[2:]
    {"sbatch": sbatch, "srun": srun, "sinfo": sinfo, "run": lambda _: run_queue()}[command](arguments)

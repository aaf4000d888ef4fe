"""The client: one method per route of rigd's ``/api/v1``, thin over httpx."""

from __future__ import annotations

import datetime as _dt
import json as _json
import os
import time
from pathlib import Path
from typing import (
    Any,
    Dict,
    Iterable,
    Iterator,
    List,
    Mapping,
    Optional,
    Sequence,
    Tuple,
    Union,
)

import httpx

from ._errors import RigdError, RigdTimeout
from ._types import (
    FINAL_STATES,
    JOB_FINAL_STATES,
    CommandAck,
    Enqueued,
    Event,
    Health,
    ProcessJob,
    QueueItem,
    Render,
    RunPage,
    RunView,
)

PathLike = Union[str, "os.PathLike[str]"]
Direction = Union[Tuple[float, float], Mapping[str, float]]
Plan = Union[str, Mapping[str, Any]]

DEFAULT_URL = "http://127.0.0.1:8080"
_CHUNK = 1 << 16


def resolve_token(token: Optional[str] = None, data_dir: Optional[PathLike] = None) -> Optional[str]:
    """The API token: ``token``, else ``$RIGD_TOKEN``, else the ``token`` file of
    ``data_dir`` or ``$RIGD_DATA``; None when there is none (reads from loopback
    need none)."""
    if token:
        return token.strip()
    env = os.environ.get("RIGD_TOKEN")
    if env:
        return env.strip()
    data = data_dir if data_dir is not None else os.environ.get("RIGD_DATA")
    if data:
        path = Path(data) / "token"
        try:
            return path.read_text(encoding="utf-8").strip()
        except OSError as e:
            # A named data directory without a readable token is a mistake worth saying.
            raise RigdError(0, "no_token", f"cannot read the token file {path}: {e}") from None
    return None


def direction(d: Direction) -> Dict[str, float]:
    """``(theta_deg, phi_deg)`` or a mapping → rigd's ``{theta_deg, phi_deg}``."""
    if isinstance(d, Mapping):
        return {"theta_deg": float(d["theta_deg"]), "phi_deg": float(d["phi_deg"])}
    theta, phi = d
    return {"theta_deg": float(theta), "phi_deg": float(phi)}


def inline_plan(
    directions: Optional[Iterable[Direction]] = None,
    *,
    lights: Optional[Iterable[Direction]] = None,
    views: Optional[Iterable[Direction]] = None,
    pairs: Optional[Iterable[Tuple[Direction, Direction]]] = None,
    name: Optional[str] = None,
) -> Dict[str, Any]:
    """An inline plan: ``directions`` (all paired with all), ``lights`` with
    ``views``, or ``pairs`` of (light, view)."""
    plan: Dict[str, Any] = {}
    if directions is not None:
        plan["directions"] = [direction(d) for d in directions]
    if lights is not None:
        plan["lights"] = [direction(d) for d in lights]
    if views is not None:
        plan["views"] = [direction(d) for d in views]
    if pairs is not None:
        plan["pairs"] = [{"light": direction(l), "view": direction(v)} for l, v in pairs]
    if name is not None:
        plan["name"] = name
    return plan


def run_request(
    sample: str,
    plan: Plan,
    *,
    operator: Optional[str] = None,
    notes: Optional[str] = None,
    exposure_s: Optional[float] = None,
    frame_size: Optional[Tuple[int, int]] = None,
    order: Optional[str] = None,
    process: Optional[Mapping[str, Any]] = None,
) -> Dict[str, Any]:
    """The body of ``POST /runs`` and ``POST /queue`` (None fields left out)."""
    body: Dict[str, Any] = {"sample": sample, "plan": plan if isinstance(plan, str) else dict(plan)}
    for key, value in (
        ("operator", operator),
        ("notes", notes),
        ("exposure_s", exposure_s),
        ("order", order),
        ("process", dict(process) if process is not None else None),
    ):
        if value is not None:
            body[key] = value
    if frame_size is not None:
        body["frame_size"] = [int(frame_size[0]), int(frame_size[1])]
    return body


def _run_id(run: Union[str, Mapping[str, Any]]) -> str:
    """Accepts a run id or a run view."""
    return run if isinstance(run, str) else str(run["id"])


def _timestamp(t: Union[None, str, _dt.datetime, _dt.date]) -> Optional[str]:
    if t is None or isinstance(t, str):
        return t
    if isinstance(t, _dt.datetime):
        if t.tzinfo is None:
            t = t.replace(tzinfo=_dt.timezone.utc)
        return t.astimezone(_dt.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ")
    return t.isoformat()


def _pair(v: Union[None, str, Sequence[float]], sep: str = ",") -> Optional[str]:
    if v is None or isinstance(v, str):
        return v
    return sep.join(f"{x:g}" if isinstance(x, float) else str(x) for x in v)


def is_fault_pause(run: Mapping[str, Any]) -> bool:
    """True for a run paused by an error (a device fault, a full disk, an
    emergency stop) rather than by the operator or a daemon shutdown.

    rigd has no field for the kind of pause; a fault pause is the one whose
    ``reason`` is the ``last_error`` it recorded (an operator pause says
    "paused by operator", a shutdown "detached", and neither sets
    ``last_error`` to its reason).
    """
    return (
        run.get("state") == "paused"
        and bool(run.get("last_error"))
        and run.get("reason") == run.get("last_error")
    )


class Client:
    """A client of one rigd daemon.

    ``url`` is the daemon's address (``http://HOST:PORT``; a trailing
    ``/api/v1`` is accepted). The token comes from ``token``, else
    ``$RIGD_TOKEN``, else ``DATA/token`` of ``data_dir`` or ``$RIGD_DATA``.
    ``timeout`` bounds every request (seconds); the event stream and
    downloads have their own.

    Every non-2xx answer raises :class:`RigdError`; a daemon that cannot be
    reached raises httpx's ``TransportError`` (``ConnectError``, …).
    """

    def __init__(
        self,
        url: Optional[str] = None,
        *,
        token: Optional[str] = None,
        data_dir: Optional[PathLike] = None,
        timeout: float = 60.0,
        transport: Optional[httpx.BaseTransport] = None,
    ) -> None:
        url = (url or os.environ.get("RIGD_URL") or DEFAULT_URL).rstrip("/")
        if url.endswith("/api/v1"):
            url = url[: -len("/api/v1")]
        self.url = url
        self.api = url + "/api/v1"
        self.token = resolve_token(token, data_dir)
        self.timeout = timeout
        headers = {"Accept": "application/json"}
        if self.token:
            headers["Authorization"] = f"Bearer {self.token}"
        self._http = httpx.Client(
            base_url=self.api, headers=headers, timeout=timeout, transport=transport
        )

    # -- plumbing -------------------------------------------------------

    def close(self) -> None:
        """Closes the connection pool."""
        self._http.close()

    def __enter__(self) -> "Client":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _error(self, r: httpx.Response, body: Optional[bytes] = None) -> RigdError:
        raw = body if body is not None else r.content
        error: Optional[str] = None
        detail = ""
        try:
            parsed = _json.loads(raw) if raw else None
        except ValueError:
            parsed = None
        if isinstance(parsed, dict) and "error" in parsed:
            error = str(parsed.get("error"))
            detail = str(parsed.get("detail", ""))
        else:
            detail = raw[:500].decode("utf-8", "replace") if raw else r.reason_phrase
        hint = ""
        if r.status_code == 401 and not self.token:
            hint = "no token given: pass token=, set RIGD_TOKEN, or point data_dir=/RIGD_DATA at the daemon's data directory"
        return RigdError(
            r.status_code, error, detail, method=r.request.method, url=r.request.url.path, hint=hint
        )

    def _request(
        self,
        method: str,
        path: str,
        *,
        json: Any = None,
        params: Optional[Mapping[str, Any]] = None,
        timeout: Optional[float] = None,
    ) -> httpx.Response:
        kwargs: Dict[str, Any] = {}
        if json is not None:
            kwargs["json"] = json
        if params:
            kwargs["params"] = {k: _param(v) for k, v in params.items() if v is not None}
        if timeout is not None:
            kwargs["timeout"] = timeout
        r = self._http.request(method, path, **kwargs)
        if not r.is_success:
            raise self._error(r)
        return r

    def _get(self, path: str, **kw: Any) -> Any:
        return self._request("GET", path, **kw).json()

    def _post(self, path: str, body: Any = None, **kw: Any) -> Any:
        r = self._request("POST", path, json=body, **kw)
        return r.json() if r.content else None

    def _bytes(self, path: str, params: Optional[Mapping[str, Any]] = None) -> bytes:
        return self._request("GET", path, params=params).content

    # -- daemon ---------------------------------------------------------

    def health(self) -> Health:
        """``GET /health``: ``{ok, version, profile, sim, sim_speed}``."""
        return self._get("/health")

    def openapi(self) -> Dict[str, Any]:
        """``GET /openapi.json``: the daemon's OpenAPI 3 spec."""
        return self._get("/openapi.json")

    # -- rig ------------------------------------------------------------

    def rig(self) -> Dict[str, Any]:
        """``GET /rig``: profile, state, active run, every device's live state, lamps."""
        return self._get("/rig")

    def rig_check(self, timeout: Optional[float] = None) -> Dict[str, Any]:
        """``GET /rig/check``: bring-up without moving anything, a verdict per device
        (409 while a run holds the rig)."""
        return self._get("/rig/check", timeout=timeout)

    def estop(self) -> Dict[str, Any]:
        """``POST /estop``: every device stops; the active run pauses (resume re-homes)."""
        return self._post("/estop")

    # -- manual control ---------------------------------------------------

    def manual_home(self, device: str) -> Dict[str, Any]:
        """``POST /rig/manual/home``: homes an axis or the arm; ``{device, position_deg}``."""
        return self._post("/rig/manual/home", {"device": device})

    def manual_jog(
        self, device: str, *, by_deg: Optional[float] = None, to_deg: Optional[float] = None
    ) -> Dict[str, Any]:
        """``POST /rig/manual/jog``: moves a homed axis by ``by_deg`` or to ``to_deg``
        (exactly one); beyond its soft limits 422 and nothing moves."""
        if (by_deg is None) == (to_deg is None):
            raise ValueError("manual_jog takes exactly one of by_deg and to_deg")
        body: Dict[str, Any] = {"device": device}
        if by_deg is not None:
            body["by_deg"] = by_deg
        else:
            body["to_deg"] = to_deg
        return self._post("/rig/manual/jog", body)

    def manual_pose(self, light: Direction, view: Direction) -> Dict[str, Any]:
        """``POST /rig/manual/pose``: moves the homed axes and arm to a (light, view)
        pair's pose; answers positions, lamp, camera, ``feasible``, ``reason``."""
        return self._post("/rig/manual/pose", {"light": direction(light), "view": direction(view)})

    def manual_lamp(self, device: str, on: bool) -> Dict[str, Any]:
        """``POST /rig/manual/lamp``: switches a lamp or the laser; ``{device, on}`` read back."""
        return self._post("/rig/manual/lamp", {"device": device, "on": bool(on)})

    def manual_frame(
        self, camera: Optional[str] = None, exposure_s: Optional[float] = None
    ) -> Dict[str, Any]:
        """``POST /rig/manual/frame``: takes a test frame; its numbers
        (``width``, ``height``, ``min``, ``max``, ``mean``, ``saturated``…)."""
        body: Dict[str, Any] = {}
        if camera is not None:
            body["camera"] = camera
        if exposure_s is not None:
            body["exposure_s"] = exposure_s
        return self._post("/rig/manual/frame", body)

    def manual_frame_png(self) -> bytes:
        """``GET /rig/manual/frame``: the last test frame as an 8-bit PNG (404 before one)."""
        return self._bytes("/rig/manual/frame")

    def manual_holder_check(
        self, camera: Optional[str] = None, exposure_s: Optional[float] = None
    ) -> Dict[str, Any]:
        """``POST /rig/manual/holder-check``: takes a test frame at the last pose and
        finds the profile's holder in it, as ``rigd holder check`` does: ``markers``,
        ``markers_found``, ``registered``, ``rms_px``/``max_px``, ``patches`` and
        ``whites`` (``name``, ``mean``, ``clipped``), ``problems``, ``ok``. A check
        that finds problems is still answered (``ok`` false); 409 before a pose."""
        body: Dict[str, Any] = {}
        if camera is not None:
            body["camera"] = camera
        if exposure_s is not None:
            body["exposure_s"] = exposure_s
        return self._post("/rig/manual/holder-check", body)

    def manual_release(self) -> None:
        """``POST /rig/manual/release``: lets go of the manual-control rig (204)."""
        self._request("POST", "/rig/manual/release")

    # -- plans ----------------------------------------------------------

    def plans(self) -> Dict[str, Any]:
        """``GET /plans``: ``{profile, plans: [{name, ready, fits, steps_total,
        estimated_physical_s, raw_bytes, …}]}``; answers at once (``ready`` false
        while the daemon still solves a plan)."""
        return self._get("/plans")

    def plan(self, name: str, timeout: Optional[float] = None) -> Dict[str, Any]:
        """``GET /plans/{name}``: one built-in plan with every step; the daemon waits
        for a plan it is still solving, so ``timeout`` may need to be long."""
        return self._get(f"/plans/{_seg(name)}", timeout=timeout)

    # -- runs -------------------------------------------------------------

    def runs(
        self,
        limit: Optional[int] = None,
        cursor: Optional[str] = None,
        sample: Optional[str] = None,
        state: Optional[str] = None,
        plan: Optional[str] = None,
        profile: Optional[str] = None,
        from_: Union[None, str, _dt.datetime] = None,
        to: Union[None, str, _dt.datetime] = None,
    ) -> RunPage:
        """``GET /runs``: one page of the run history, newest first.

        ``cursor`` is a page's ``next``; the filters go as the query parameters
        of the same names (``from_`` as ``from``; datetimes as RFC 3339 UTC).
        """
        params = {
            "limit": limit,
            "cursor": cursor,
            "sample": sample,
            "state": state,
            "plan": plan,
            "profile": profile,
            "from": _timestamp(from_),
            "to": _timestamp(to),
        }
        body = self._get("/runs", params=params)
        total = body.get("total")
        return RunPage(
            runs=list(body.get("runs", [])),
            active=body.get("active"),
            next=body.get("next") or None,
            total=int(total) if total is not None else None,
            raw=body,
        )

    def iter_runs(
        self,
        limit: Optional[int] = None,
        sample: Optional[str] = None,
        state: Optional[str] = None,
        plan: Optional[str] = None,
        profile: Optional[str] = None,
        from_: Union[None, str, _dt.datetime] = None,
        to: Union[None, str, _dt.datetime] = None,
        max_pages: int = 100_000,
    ) -> Iterator[RunView]:
        """Every run matching the filters, following ``next`` cursors; ``limit``
        is the page size. Stops at a cursor seen before (a daemon bug would
        otherwise loop forever) by raising RuntimeError."""
        cursor: Optional[str] = None
        seen = set()
        for _ in range(max_pages):
            page = self.runs(limit, cursor, sample, state, plan, profile, from_, to)
            yield from page.runs
            if page.next is None:
                return
            if page.next in seen:
                raise RuntimeError(f"GET /runs returned the cursor {page.next!r} twice")
            seen.add(page.next)
            cursor = page.next
        raise RuntimeError(f"GET /runs: more than {max_pages} pages")

    def run(self, run: Union[str, Mapping[str, Any]]) -> RunView:
        """``GET /runs/{id}``: state, reason, last_error, progress, ETAs, processing."""
        return self._get(f"/runs/{_seg(_run_id(run))}")

    def start_run(self, sample: str, plan: Plan, **options: Any) -> RunView:
        """``POST /runs``: starts a run now (201 with the run; 409 while another is
        active). ``options`` are :func:`run_request`'s: operator, notes,
        exposure_s, frame_size, order, process."""
        return self._post("/runs", run_request(sample, plan, **options))

    def steps(self, run: Union[str, Mapping[str, Any]]) -> Dict[str, Any]:
        """``GET /runs/{id}/steps``: every image of the plan with ``done``."""
        return self._get(f"/runs/{_seg(_run_id(run))}/steps")

    def manifest(self, run: Union[str, Mapping[str, Any]]) -> Dict[str, Any]:
        """``GET /runs/{id}/manifest``: manifest.json (404 until completed or aborted)."""
        return self._get(f"/runs/{_seg(_run_id(run))}/manifest")

    def pause(self, run: Union[str, Mapping[str, Any]]) -> CommandAck:
        """``POST /runs/{id}/pause``: the engine pauses after the step in flight."""
        return self._post(f"/runs/{_seg(_run_id(run))}/pause")

    def resume(self, run: Union[str, Mapping[str, Any]], reference_confirmed: bool = False) -> CommandAck:
        """``POST /runs/{id}/resume[?reference_confirmed=true]``: continues a paused
        or interrupted run."""
        params = {"reference_confirmed": True} if reference_confirmed else None
        return self._post(f"/runs/{_seg(_run_id(run))}/resume", params=params)

    def abort(self, run: Union[str, Mapping[str, Any]]) -> CommandAck:
        """``POST /runs/{id}/abort``: aborts a run (the live engine writes its manifest)."""
        return self._post(f"/runs/{_seg(_run_id(run))}/abort")

    def frame(self, run: Union[str, Mapping[str, Any]], index: int) -> bytes:
        """``GET /runs/{id}/frames/{index}``: the frame as stored (a PNG of the sensor
        values, or the camera's own file)."""
        return self._bytes(f"/runs/{_seg(_run_id(run))}/frames/{int(index)}")

    def frame_preview(self, run: Union[str, Mapping[str, Any]], index: int) -> bytes:
        """``GET /runs/{id}/frames/{index}/preview``: an 8-bit PNG, at most 256 px."""
        return self._bytes(f"/runs/{_seg(_run_id(run))}/frames/{int(index)}/preview")

    def wait(
        self,
        run: Union[str, Mapping[str, Any]],
        timeout: float = 600.0,
        *,
        poll: float = 0.2,
        stop_on_pause: bool = False,
        until: Optional[Iterable[str]] = None,
    ) -> RunView:
        """Waits until the run is final (completed, failed, aborted), paused by an
        error (:func:`is_fault_pause`) or ``interrupted`` (the daemon died; only
        the operator moves it on), and returns its view. ``stop_on_pause`` also
        returns on any pause; ``until`` returns only on those states (e.g.
        ``{"aborted"}`` after aborting a run that is paused by a fault, whose
        state changes a moment after the command). Raises :class:`RigdTimeout`
        after ``timeout`` s."""
        wanted = frozenset(until) if until is not None else None
        deadline = time.monotonic() + timeout
        ident = _run_id(run)
        view: Optional[RunView] = None
        while True:
            view = self.run(ident)
            state = view.get("state")
            if wanted is not None:
                if state in wanted:
                    return view
            elif (
                state in FINAL_STATES
                or state == "interrupted"
                or is_fault_pause(view)
                or (stop_on_pause and state == "paused")
            ):
                return view
            left = deadline - time.monotonic()
            if left <= 0:
                raise RigdTimeout(
                    f"run {ident} still {state} ({view.get('steps_done')}/{view.get('steps_total')}) after {timeout:g} s",
                    dict(view),
                )
            time.sleep(min(poll, left))

    # -- queue ------------------------------------------------------------

    def queue(self) -> List[QueueItem]:
        """``GET /queue``: the queued runs in order (the ``items``)."""
        return list(self._get("/queue").get("items", []))

    def enqueue(self, sample: str, plan: Plan, **options: Any) -> Enqueued:
        """``POST /queue``: queues a run (same fields as :meth:`start_run`);
        ``{item, started_run}``, the run set when it started at once."""
        return self._post("/queue", run_request(sample, plan, **options))

    def dequeue(self, item: Union[str, Mapping[str, Any]]) -> None:
        """``DELETE /queue/{item}``: removes a queued run (204; 404 when gone)."""
        ident = item if isinstance(item, str) else str(item["id"])
        self._request("DELETE", f"/queue/{_seg(ident)}")

    # -- processing -----------------------------------------------------

    def process(
        self,
        run: Union[str, Mapping[str, Any]],
        *steps: str,
        wait: bool = False,
        timeout: float = 600.0,
        rectify: Optional[Mapping[str, Any]] = None,
        btf: Optional[Mapping[str, Any]] = None,
        fit: Optional[Mapping[str, Any]] = None,
        mdf: Optional[Mapping[str, Any]] = None,
        photometric_stereo: Optional[Mapping[str, Any]] = None,
    ) -> ProcessJob:
        """``POST /runs/{id}/process``: processes an ended run in the daemon.

        ``steps`` among rectify, btf, fit, mdf, photometric-stereo (none: the
        daemon picks them from the run); the keyword options are each step's
        (e.g. ``btf={"components": 8}``). Asking again with the same options
        returns the same job. With ``wait`` it returns the job once it is done
        or failed (see :meth:`wait_process`)."""
        body: Dict[str, Any] = {}
        if steps:
            body["steps"] = list(steps)
        for key, value in (
            ("rectify", rectify),
            ("btf", btf),
            ("fit", fit),
            ("mdf", mdf),
            ("photometric_stereo", photometric_stereo),
        ):
            if value is not None:
                body[key] = dict(value)
        job: ProcessJob = self._post(f"/runs/{_seg(_run_id(run))}/process", body)
        if wait:
            return self.wait_process(run, timeout=timeout)
        return job

    def process_job(self, run: Union[str, Mapping[str, Any]]) -> ProcessJob:
        """``GET /runs/{id}/process``: the run's job (404 without one)."""
        return self._get(f"/runs/{_seg(_run_id(run))}/process")

    def cancel_process(self, run: Union[str, Mapping[str, Any]]) -> ProcessJob:
        """``POST /runs/{id}/process/cancel``: drops a queued job, stops a running
        one (``cancelling`` until it does); 409 when it has ended."""
        return self._post(f"/runs/{_seg(_run_id(run))}/process/cancel")

    def wait_process(
        self, run: Union[str, Mapping[str, Any]], timeout: float = 600.0, *, poll: float = 0.25
    ) -> ProcessJob:
        """Waits until the run's job is done or failed and returns it (check
        ``state`` and ``error``); :class:`RigdTimeout` after ``timeout`` s."""
        deadline = time.monotonic() + timeout
        while True:
            job = self.process_job(run)
            if job.get("state") in JOB_FINAL_STATES:
                return job
            left = deadline - time.monotonic()
            if left <= 0:
                raise RigdTimeout(
                    f"process job of {_run_id(run)} still {job.get('state')} after {timeout:g} s", dict(job)
                )
            time.sleep(min(poll, left))

    # -- viewer data ------------------------------------------------------

    def btf(self, run: Union[str, Mapping[str, Any]], components: Optional[int] = None) -> Dict[str, Any]:
        """``GET /runs/{id}/btf[?components=C]``: the processed material's manifest
        (``kind`` btf or photometric-stereo, sizes, sections, ``data_url``)."""
        return self._get(f"/runs/{_seg(_run_id(run))}/btf", params={"components": components})

    def btf_data(self, run: Union[str, Mapping[str, Any]], components: Optional[int] = None) -> bytes:
        """``GET /runs/{id}/btf/data[?components=C]``: the packed material."""
        return self._bytes(f"/runs/{_seg(_run_id(run))}/btf/data", params={"components": components})

    def btf_mesh(
        self, run: Union[str, Mapping[str, Any]], kind: str = "flat", density: Optional[float] = None
    ) -> Dict[str, Any]:
        """``GET /runs/{id}/btf/mesh/{kind}[?density=D]``: a viewer mesh (flat,
        cylinder, cloth, sphere) with per-vertex light visibility."""
        return self._get(
            f"/runs/{_seg(_run_id(run))}/btf/mesh/{_seg(kind)}", params={"density": density}
        )

    def mdf(self, run: Union[str, Mapping[str, Any]]) -> Dict[str, Any]:
        """``GET /runs/{id}/mdf``: the MDF texture's manifest (404 without one)."""
        return self._get(f"/runs/{_seg(_run_id(run))}/mdf")

    def mdf_data(self, run: Union[str, Mapping[str, Any]]) -> bytes:
        """``GET /runs/{id}/mdf/data``: the depths, f32 layers, one per view."""
        return self._bytes(f"/runs/{_seg(_run_id(run))}/mdf/data")

    # -- downloads --------------------------------------------------------

    def download(
        self,
        run: Union[str, Mapping[str, Any]],
        what: str,
        dest: PathLike,
        *,
        indices: Optional[Iterable[int]] = None,
        components: Optional[int] = None,
        timeout: float = 600.0,
    ) -> List[Path]:
        """Streams a run's files into the directory ``dest`` and returns their paths.

        ``what``: ``frames`` (every captured frame as stored, ``frames/NNNNNN.EXT``;
        or only ``indices``), ``previews`` (``previews/NNNNNN.png``),
        ``manifest`` (``manifest.json``), ``steps`` (``steps.json``), ``btf``
        (``btf.json`` and ``btf.bin``, at most ``components`` per slot) or
        ``mdf`` (``mdf.json`` and ``mdf.bin``). Files are written under a
        temporary name and renamed, so a cut download leaves no partial file.
        """
        ident = _seg(_run_id(run))
        out = Path(dest)
        out.mkdir(parents=True, exist_ok=True)
        base = f"/runs/{ident}"
        if what in ("frames", "previews"):
            if indices is None:
                indices = [s["index"] for s in self.steps(run)["steps"] if s.get("done")]
            sub = out / what
            sub.mkdir(exist_ok=True)
            written = []
            for i in indices:
                suffix = "/preview" if what == "previews" else ""
                written.append(self._stream_to(f"{base}/frames/{int(i)}{suffix}", sub / f"{int(i):06d}", None, timeout))
            return written
        if what == "manifest":
            return [self._stream_to(f"{base}/manifest", out / "manifest.json", None, timeout)]
        if what == "steps":
            return [self._stream_to(f"{base}/steps", out / "steps.json", None, timeout)]
        if what == "btf":
            params = {"components": components}
            return [
                self._stream_to(f"{base}/btf", out / "btf.json", params, timeout),
                self._stream_to(f"{base}/btf/data", out / "btf.bin", params, timeout),
            ]
        if what == "mdf":
            return [
                self._stream_to(f"{base}/mdf", out / "mdf.json", None, timeout),
                self._stream_to(f"{base}/mdf/data", out / "mdf.bin", None, timeout),
            ]
        raise ValueError(f"download: unknown {what!r}; frames, previews, manifest, steps, btf or mdf")

    def _stream_to(
        self, path: str, target: Path, params: Optional[Mapping[str, Any]], timeout: float
    ) -> Path:
        """GETs ``path`` into ``target``; a name without a suffix gets one from the
        content type (frames may be PNG, DNG, JPEG, TIFF or raw)."""
        query = {k: _param(v) for k, v in (params or {}).items() if v is not None}
        with self._http.stream("GET", path, params=query, timeout=timeout) as r:
            if not r.is_success:
                raise self._error(r, r.read())
            if not target.suffix:
                target = target.with_suffix(_suffix(r.headers.get("content-type", "")))
            tmp = target.with_name(target.name + ".part")
            try:
                with open(tmp, "wb") as f:
                    for chunk in r.iter_bytes(_CHUNK):
                        f.write(chunk)
                os.replace(tmp, target)
            finally:
                if tmp.exists():
                    tmp.unlink()
        return target

    # -- events -----------------------------------------------------------

    def events(
        self,
        last_event_id: Optional[int] = None,
        *,
        reconnect: bool = True,
        max_backoff: float = 10.0,
        give_up_after: Optional[float] = 120.0,
        read_timeout: float = 45.0,
    ) -> Iterator[Event]:
        """``GET /events``: the daemon's Server-Sent Events as :class:`Event` s.

        ``last_event_id`` replays the kept events after it (rigd keeps the last
        4096). A dropped connection (or silence beyond ``read_timeout``: rigd
        sends a keep-alive every 15 s) is reconnected with ``Last-Event-ID``
        set to the last id received, after a backoff of 0.25 s doubling to
        ``max_backoff``; after ``give_up_after`` seconds without getting
        through (None: never) the last error is raised. An HTTP error answer
        (e.g. 503 too many streams) raises :class:`RigdError` unless it is a
        503, which is retried like a dropped connection.

        Close the generator (or break out of the loop) to stop.
        """
        last = last_event_id
        backoff = 0.25
        failing_since: Optional[float] = None
        timeout = httpx.Timeout(self.timeout, read=read_timeout)
        while True:
            if self._http.is_closed:
                return  # the client was closed (from another thread): the stream ends
            headers = {"Accept": "text/event-stream"}
            if last is not None:
                headers["Last-Event-ID"] = str(last)
            try:
                with self._http.stream("GET", "/events", headers=headers, timeout=timeout) as r:
                    if not r.is_success:
                        err = self._error(r, r.read())
                        if r.status_code != 503 or not reconnect:
                            raise err
                        raise _Retry(err)
                    backoff, failing_since = 0.25, None
                    for ev in _parse_sse(r.iter_lines()):
                        if ev.id is not None:
                            last = ev.id
                        yield ev
                # The server ended the stream (e.g. shutting down): reconnect below.
                error: BaseException = ConnectionError("the event stream ended")
            except (httpx.TransportError, _Retry) as e:
                error = e.err if isinstance(e, _Retry) else e
            if not reconnect:
                return
            now = time.monotonic()
            if failing_since is None:
                failing_since = now
            elif give_up_after is not None and now - failing_since > give_up_after:
                raise error
            time.sleep(backoff)
            backoff = min(backoff * 2, max_backoff)

    # -- simulation ---------------------------------------------------------

    def sim_scenes(self) -> List[Dict[str, Any]]:
        """``GET /sim/scenes``: ``[{name, description, effects}]``."""
        return self._get("/sim/scenes")

    def sim_render(
        self,
        scene: Optional[str] = None,
        *,
        light: Union[None, str, Sequence[float]] = None,
        view: Union[None, str, Sequence[float]] = None,
        size: Union[None, str, Sequence[int]] = None,
        camera: Optional[str] = None,
        effects: Optional[str] = None,
        seed: Optional[int] = None,
        exposure: Optional[float] = None,
        laser: Union[None, str, Sequence[float]] = None,
        lamp_off: Optional[bool] = None,
        zoom: Optional[float] = None,
    ) -> Render:
        """``GET /sim/render``: one frame of a scene through the profile's camera.
        ``light``/``view`` are (θ, φ) degrees, ``size`` (W, H), ``laser`` (X,
        TILT); the answer is the PNG with ``X-Rigd-Effects`` and
        ``X-Rigd-Render-Ms``."""
        params = {
            "scene": scene,
            "light": _pair(light),
            "view": _pair(view),
            "size": _pair(size, "x"),
            "camera": camera,
            "effects": effects,
            "seed": seed,
            "exposure": exposure,
            "laser": _pair(laser),
            "lamp_off": lamp_off,
            "zoom": zoom,
        }
        r = self._request("GET", "/sim/render", params=params)
        eff = r.headers.get("x-rigd-effects", "")
        ms = r.headers.get("x-rigd-render-ms")
        try:
            render_ms: Optional[float] = float(ms) if ms is not None else None
        except ValueError:
            render_ms = None
        return Render(r.content, [e for e in (x.strip() for x in eff.split(",")) if e], render_ms)

    # -- trade-off --------------------------------------------------------

    def tradeoff(self) -> Dict[str, Any]:
        """``GET /tradeoff``: the latest trade-off report (404 until there is one)."""
        return self._get("/tradeoff")

    def tradeoff_plot(self) -> str:
        """``GET /tradeoff/plot.svg``: the report's figure as SVG text."""
        return self._request("GET", "/tradeoff/plot.svg").text

    def tradeoff_figure(self) -> Dict[str, Any]:
        """``GET /tradeoff/figure``: the figure with its layout (panels, points)."""
        return self._get("/tradeoff/figure")

    def tradeoff_choice(self, *, budget: Optional[str] = None, target: Optional[str] = None) -> Dict[str, Any]:
        """``GET /tradeoff/choice``: the most accurate plan within ``budget``
        (``3h``, ``90m``, seconds) or the fastest reaching ``target`` (``15%``,
        ``0.15``): ``{goal, plan, frontier, answer}``."""
        return self._get("/tradeoff/choice", params={"budget": budget, "target": target})

    def start_tradeoff(
        self,
        scene: Optional[str] = None,
        *,
        texture: Optional[int] = None,
        held_out: Optional[int] = None,
        render_size: Optional[Tuple[int, int]] = None,
    ) -> Dict[str, Any]:
        """``POST /tradeoff``: computes the report in the background (202);
        ``tradeoff`` events report progress."""
        body: Dict[str, Any] = {}
        if scene is not None:
            body["scene"] = scene
        if texture is not None:
            body["texture"] = texture
        if held_out is not None:
            body["held_out"] = held_out
        if render_size is not None:
            body["render_size"] = [int(render_size[0]), int(render_size[1])]
        return self._post("/tradeoff", body)

    # -- peers --------------------------------------------------------------

    def peers(self) -> List[Dict[str, Any]]:
        """``GET /peers``: this rig first, then each peer as last polled."""
        return list(self._get("/peers").get("peers", []))

    def pause_peer(self, name: str) -> CommandAck:
        """``POST /peers/{name}/pause``: pauses a peer's active run (the peer's answer)."""
        return self._post(f"/peers/{_seg(name)}/pause")

    def abort_peer(self, name: str) -> CommandAck:
        """``POST /peers/{name}/abort``: aborts a peer's active run (the peer's answer)."""
        return self._post(f"/peers/{_seg(name)}/abort")


class _Retry(Exception):
    """An answer worth retrying (503), carried out of the stream's context."""

    def __init__(self, err: RigdError) -> None:
        super().__init__(str(err))
        self.err = err


def _parse_sse(lines: Iterable[str]) -> Iterator[Event]:
    """Server-Sent Events framing: fields until a blank line; ``:`` lines are
    comments (rigd's keep-alive)."""
    data: List[str] = []
    sse_id: Optional[str] = None
    name = "message"
    for line in lines:
        if line == "":
            if data:
                yield Event.from_sse(sse_id, name, "\n".join(data))
            data, sse_id, name = [], None, "message"
            continue
        if line.startswith(":"):
            continue
        key, _, value = line.partition(":")
        if value.startswith(" "):
            value = value[1:]
        if key == "data":
            data.append(value)
        elif key == "id":
            sse_id = value
        elif key == "event":
            name = value or "message"
    if data:
        yield Event.from_sse(sse_id, name, "\n".join(data))


def _seg(s: str) -> str:
    """A path segment, percent-encoded (rigd looks names up; it never takes paths)."""
    from urllib.parse import quote

    return quote(str(s), safe="")


def _param(v: Any) -> Any:
    if isinstance(v, bool):
        return "true" if v else "false"
    return v


def _suffix(content_type: str) -> str:
    ct = content_type.split(";")[0].strip().lower()
    return {
        "image/png": ".png",
        "image/jpeg": ".jpg",
        "image/tiff": ".tiff",
        "image/x-adobe-dng": ".dng",
        "application/json": ".json",
    }.get(ct, ".bin")

"""Solver service: on ``fragment.ready``, turn raw flatbed scans into RGBN faces (§3.3.6).

Reads the ``tessera.scans`` artifact, takes the newest valid calibration of the scanning device,
checks the declared dpi and sizes (:mod:`common.limits`: an absurd scan is rejected at once),
registers each face's scans to its first scan and solves albedo + normals
(:func:`common.acquisition.flatbed_normals.solve_face`), writes one ``tessera.rgbn`` artifact per
face at a content-keyed path and returns one ``rgbn.ready`` per face. A colour-only capture gives
albedo only — and only an explicitly colour-only one: a face with one or two scans in a capture
for normals is rejected (normals need three), never published as albedo alone. Scans are checked
first (:func:`~common.acquisition.capture.check_capture`: grey scans get three channels, float
scans become 16-bit; 8-bit values in a 16-bit scan, black or blank scans are rejected naming
``<face> scan <k>``, counted from 0). A face whose scans cannot be registered fails the job with
the reason (no embossed normals are published); a face with no fragment pixel is never written
or announced.

Config (``[services.solver]``): ``auto_calibrate_simulator`` (default true: a simulated device
without a calibration is calibrated on first use).
"""

from __future__ import annotations

from common.acquisition.calibration import (calibrate_scanner, newest_calibration, save_calibration,
                                            simulated_target_operator)
from common.acquisition.capture import FACES, check_capture, read_scans
from common.acquisition.errors import CalibrationError
from common.acquisition.flatbed_normals import colour_only_face, solve_face
from common.messages import MessageError, new_message
from common.rgbn.image import save_rgbn
from common.store import ArtifactError, ArtifactRef, content_key

SERVICE = "solver"
VERSION = "flatbed-ps-1.1"   # 1.1: registration image log-before-blur (issue 16)


def output_path(fragment: str, face: str, scans_sha256: str, calibration_id: str) -> str:
    """Content-keyed path of one face's RGBN artifact."""
    return f"fragments/{fragment}/rgbn/{face}-{content_key(scans_sha256, calibration_id, SERVICE, VERSION)}.h5"


def _calibration(ctx, device: str):
    try:
        return newest_calibration(ctx.store, device)
    except CalibrationError as exc:
        if not (device.startswith("sim") and (ctx.config or {}).get("auto_calibrate_simulator", True)):
            # a bare `tessera calibrate` calibrates the station's own [scanner] device, not this one:
            # name the commands that calibrate *this* device, and how to re-queue the parked job
            raise CalibrationError(
                f"{exc} for this device: with scans of a tilted target `tessera calibrate --from-files MANIFEST "
                f"--device {device}`, without `tessera calibrate --nominal --lamp-direction-deg D --device {device}` "
                f"(D: the lamp side `tessera import scans` logged); then re-queue the parked job "
                f"(`tessera status --rerun JOB`)") from None
    from common.acquisition.flatbed_sim import SimulatedFlatbed
    ctx.log.info("no calibration for simulated device %s: calibrating it now", device)
    sim = SimulatedFlatbed(device)
    cal = calibrate_scanner(sim, simulated_target_operator(sim), area_mm=(50, 50, 70, 70))
    ref = save_calibration(ctx.store, cal)
    return cal, ref


def handle(job: dict, ctx) -> list[dict]:
    """Solve every face of the fragment named by a ``fragment.ready`` job; return ``rgbn.ready`` events."""
    if job.get("type") != "fragment.ready":
        raise MessageError(f"solver handles fragment.ready, got {job.get('type')!r}")
    ref = ArtifactRef.from_dict(job["artifact"])
    fragment = str(job["fragment"])
    ctx.progress(0.0, "reading scans")
    capture = read_scans(ctx.store, ref, check_limits=True)  # absurd dpi or sizes: rejected before a pixel is read
    # the artifact says which scanner made the scans and whether they are colour-only; the message's copies
    # (docs/messages.md) must agree, or the calibration the sender meant is not the one that would be used
    for field, held in (("device", capture.device), ("colour_only", bool(capture.colour_only))):
        if field in job and job[field] != held:
            raise MessageError(f"fragment.ready for {fragment}: its {field} {job[field]!r} contradicts the scans "
                               f"artifact {ref.path}, whose {field} is {held!r} (the artifact's is used for the "
                               "calibration and the solve): re-import the scans with the right one")
    try:  # float, grey, 8-bit-in-16, blank scans; a face with 1-2 scans that is not colour-only
        capture = check_capture(capture)
    except ValueError as exc:
        raise ArtifactError(f"scans {ref.path}: {exc}") from exc
    cal, cal_ref = _calibration(ctx, capture.device)
    events = []
    faces = [f for f in FACES if capture.scans.get(f)]
    for k, face in enumerate(faces):
        scans = capture.scans[face]
        relpath = output_path(fragment, face, ref.sha256, cal_ref.sha256)
        if not ctx.store.exists(relpath):
            base = k / len(faces)
            report = lambda f, t: ctx.progress(base + f / len(faces), f"{face}: {t}")
            if capture.colour_only:
                image = colour_only_face(scans[0].image, scans[0].dpi, cal.a)
                regs = []
            else:
                image, regs = solve_face([s.image for s in scans], scans[0].dpi, cal.a,
                                         nominal_deg=[s.rotation for s in scans], progress=report,
                                         a_per_mm=cal.a_per_mm, a_depth_mm=cal.a_depth_mm)
            if not image.mask.any():   # never write or announce a face with nothing in it
                raise ArtifactError(f"scans {ref.path}: {face} face: no fragment pixel found or solved; nothing "
                                    "written")
            image.attrs["face"] = face
            image.attrs["calibration"] = cal_ref.path
            ctx.log.info("fragment %s %s: %d scans, registration residual %s", fragment, face, len(scans),
                         image.attrs.get("registration_residual", "n/a"))
            out = save_rgbn(ctx.store, relpath, image, provenance={
                "stage": SERVICE, "stage_version": VERSION, "fragment": fragment, "face": face,
                "device": capture.device, "calibration": cal_ref.to_dict(), "inputs": [ref.to_dict()],
                "registration": [{"angle_deg": r.angle_deg, "correlation": r.correlation, "residual": r.residual}
                                 for r in regs]})
        else:
            out = ctx.store.ref(relpath)
        events.append(new_message("rgbn.ready", fragment=fragment, face=face, artifact=out))
    ctx.progress(1.0, "done")
    return events

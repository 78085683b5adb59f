"""``narf-view``'s server: a viser page per browser tab, the fitted field rendered as the scene's background image
with its depth (docs/guides/viewer.md).

Each tab is a :class:`Session` with its own pose, mode and camera, and one thread that renders: a preview at
``preview`` pixels on the long side as soon as anything changes, then, once nothing has changed for
``settle_seconds``, the full frame in bands of rows (a change abandons it between bands). Renders of all tabs take
turns on one lock, so two tabs share the cores instead of fighting over them. A closed tab stops its thread and
drops its state.
"""

from __future__ import annotations

import errno
import json
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from dataclasses import field as dataclass_field
from functools import lru_cache
from pathlib import Path

import cv2
import numpy as np
import torch
import viser
from scipy.spatial.transform import Rotation

from fitting.config import with_eval_samples
from fitting.evaluate import render_view
from fitting.files import atomic_write_bytes
from fitting.fitted import SavedRun, run_folder
from fitting.plots import colour_depth, colour_segmentation, to_numpy
from narf.kinematics import JOINT_NAMES
from pipelines.datasets.camera_path import CameraPath, Keyframe
from pipelines.datasets.floor import camera_up
from pipelines.viewer.avatar import AvatarPose, camera_from_viewer, viewer_from_camera, z_depth

MODES = ("RGB", "depth", "parts")


def preview_config(config):
    """The config a preview renders with: the training sample counts where they are smaller than the evaluation
    ones (the field was fitted at them; the CPU preset's 8 + 8 against 16 + 16 halves the work)."""
    render = config.render
    return with_eval_samples(
        config, min(render.train_coarse, render.eval_coarse), min(render.train_fine, render.eval_fine)
    )


@dataclass
class PoseSource:
    """Poses a tab can step through: ``count`` of them at ``fps``, ``make(k)`` the k-th."""

    name: str
    count: int
    fps: float
    make: Callable[[int], AvatarPose]


@dataclass
class Person:
    """An autoencoder run's person: the code of one training render (1, 2 L), the skeleton and camera of it."""

    name: str
    code: torch.Tensor
    rest: np.ndarray
    camera: object


@dataclass
class ViewerData:
    """What every tab shares: the field and its config, the poses a tab can show, the cameras (view presets), the
    people of an autoencoder run (empty for a subject run), the world's up axis, and the render lock."""

    field: torch.nn.Module
    config: object
    sources: list[PoseSource]
    cameras: list
    up: np.ndarray
    device: str
    out_dir: Path
    people: list[Person] = dataclass_field(default_factory=list)
    preview: int = 192
    full: int = 512
    settle_seconds: float = 0.25
    lock: threading.Lock = dataclass_field(default_factory=threading.Lock)
    #: the pose features a subject run colours a shown pose with (``LoadedRun.colour_poses``); None: its own
    colour: Callable | None = None


class Session:
    """One browser tab (module docstring)."""

    def __init__(self, data: ViewerData, client: viser.ClientHandle):
        self.data, self.client = data, client
        self.source, self.index, self.person, self.other, self.blend = data.sources[0], 0, 0, 0, 0.0
        self.pose = self._posed(0)
        self.mode, self.version, self.shown, self.full_shown = MODES[0], 0, -1, -1
        self.changed_at, self.playing, self.speed = time.monotonic(), False, 1.0
        self.keyframes: list[Keyframe] = []
        self.last_image: np.ndarray | None = None
        self.stop = threading.Event()
        self.wake = threading.Event()
        self.handles = []
        self._build_gui()
        self.show_camera(data.cameras[0])
        client.camera.on_update(lambda _: self.touch())
        self.thread = threading.Thread(target=self._loop, name=f"narf-view tab {client.client_id}", daemon=True)
        self.thread.start()

    # --- state -------------------------------------------------------------------------------------------------
    def touch(self) -> None:
        """Something changed: render again (preview first)."""
        self.version += 1
        self.changed_at = time.monotonic()
        self.wake.set()

    def _posed(self, index: int) -> AvatarPose:
        """The source's pose ``index``, on the chosen person's skeleton for an autoencoder run (retargeted)."""
        pose = self.source.make(index)
        if self.data.people:
            pose.rest = self.data.people[self.person].rest
        return pose

    def set_frame(self, source: PoseSource, index: int) -> None:
        scales = self.pose.bone_scales
        self.source, self.index = source, int(np.clip(index, 0, source.count - 1))
        self.pose = replace(self._posed(self.index), bone_scales=scales)
        self._place_handles()
        self.touch()

    def latent(self) -> torch.Tensor | None:
        """The code rendered: person A's, blended towards person B's (autoencoder runs), else None."""
        if not self.data.people:
            return None
        a, b = self.data.people[self.person].code, self.data.people[self.other].code
        return ((1 - self.blend) * a + self.blend * b).to(self.data.device)

    def show_camera(self, camera) -> None:
        """Look from a capture camera's centre at the pelvis, upright (the world's up; a rolled or portrait rig
        camera would show the avatar tilted), with the camera's vertical field of view."""
        position, _, fov = viewer_from_camera(camera)
        with self.client.atomic():
            self.client.camera.up_direction = self.data.up
            self.client.camera.fov = fov
            self.client.camera.position = position
            self.client.camera.look_at = self.pose.world_from_joint()[0, :3, 3]
        self.touch()

    # --- rendering ---------------------------------------------------------------------------------------------
    def current_camera(self, long_side: int):
        camera = self.client.camera
        return camera_from_viewer(camera.position, camera.wxyz, camera.fov, camera.aspect, long_side)

    def render(self, camera, still: bool = True) -> dict | None:
        """Render ``camera`` under the shared lock: a preview at the training sample counts in one go, or the still
        frame at the evaluation counts in bands of rows; None when a newer change (or closing) abandons it."""
        data, version, latent = self.data, self.version, self.latent()
        config = data.config if still else preview_config(data.config)
        pose = self.pose.pose_batch()
        pose = (pose if data.colour is None else data.colour(pose)).to(data.device)
        bands, band_rows = [], max(16, camera.height // 4) if still else camera.height
        for top in range(0, camera.height, band_rows):
            rows = min(band_rows, camera.height - top)
            K = camera.K.copy()
            K[1, 2] -= top
            band = replace(camera, K=K, height=rows)
            with self.data.lock:
                if self.stop.is_set() or (still and version != self.version):
                    return None
                bands.append(to_numpy(render_view(data.field, band, pose, config, latent)))
        return {key: np.concatenate([b[key] for b in bands]) for key in bands[0]}

    def picture(self, render: dict) -> np.ndarray:
        """(H, W, 3) uint8 of the tab's mode."""
        if self.mode == "depth":
            image = colour_depth(render["depth"], render["mask"])
        elif self.mode == "parts" and "segmentation" in render:
            image = colour_segmentation(render["segmentation"])
        else:
            image = render["rgb"]
        return (np.clip(image, 0, 1) * 255 + 0.5).astype(np.uint8)

    def _show(self, camera, render: dict) -> None:
        if self.stop.is_set():  # the tab has gone: nothing to send it
            return
        depth = z_depth(render["depth"], render["mask"], camera.K)
        self.last_image = self.picture(render)
        self.client.scene.set_background_image(self.last_image, format="jpeg", jpeg_quality=90, depth=depth)

    def _loop(self) -> None:
        torch.set_grad_enabled(False)
        while not self.stop.is_set():
            self.wake.wait(timeout=0.05)
            self.wake.clear()
            if self.playing:
                self._advance()
            version = self.version
            if self.client.camera.update_timestamp == 0.0:
                continue  # the page has not reported its camera yet
            try:
                if version != self.shown:
                    camera = self.current_camera(self.data.preview)
                    render = self.render(camera, still=False)
                    if render is not None:
                        self._show(camera, render)
                    self.shown = version
                elif self.full_shown != version and time.monotonic() - self.changed_at > self.data.settle_seconds:
                    camera = self.current_camera(self.data.full)
                    render = self.render(camera)
                    if render is not None and version == self.version:
                        self._show(camera, render)
                        self.full_shown = version
            except Exception as err:  # a render thread must not die silently: say it, and go on with the next change
                if self.stop.is_set():
                    return
                print(f"narf-view: tab {self.client.client_id}: {type(err).__name__}: {err}", file=sys.stderr)
                self.shown = self.full_shown = version
                time.sleep(0.5)

    def _advance(self) -> None:
        step = int((time.monotonic() - self._play_started) * self.source.fps * self.speed)
        index = (self._play_from + step) % self.source.count
        if index != self.index:
            self.frame_slider.value = index  # its callback (set_frame) moves the pose, as a drag of the slider does

    # --- controls ----------------------------------------------------------------------------------------------
    def _build_gui(self) -> None:
        gui, data = self.client.gui, self.data
        with gui.add_folder("Pose"):
            names = tuple(source.name for source in data.sources)
            self.source_menu = gui.add_dropdown("source", names, initial_value=names[0])
            self.frame_slider = gui.add_slider("frame", 0, max(self.source.count - 1, 1), 1, 0)
            self.play_button = gui.add_button("play / pause")
            self.speed_slider = gui.add_slider("speed", 0.25, 4.0, 0.25, 1.0)
            self.hand_box = gui.add_checkbox("pose by hand (joint handles)", False)
            reset = gui.add_button("reset pose")
        with gui.add_folder("Bone lengths"):
            self.bone_sliders = {name: gui.add_slider(name, 0.5, 1.5, 0.05, 1.0) for name in self.pose.bone_scales}
        if data.people:
            self._people_gui()
        with gui.add_folder("View"):
            self.mode_menu = gui.add_dropdown("show", MODES, initial_value=self.mode)
            names = tuple(c.name for c in data.cameras)
            self.camera_menu = gui.add_dropdown("training camera", names, initial_value=names[0])
            shot = gui.add_button("screenshot")
            key = gui.add_button("add camera keyframe")
            save = gui.add_button("save camera path")
        self.source_menu.on_update(lambda _: self._switch_source())
        self.frame_slider.on_update(lambda _: self.set_frame(self.source, self.frame_slider.value))
        self.play_button.on_click(lambda _: self._toggle_play())
        self.speed_slider.on_update(lambda _: self._set_speed(self.speed_slider.value))
        self.hand_box.on_update(lambda _: self._place_handles())
        reset.on_click(lambda _: self.set_frame(self.source, self.index))
        for name, slider in self.bone_sliders.items():
            slider.on_update(lambda _, n=name, s=slider: self._scale_bones(n, s.value))
        self.mode_menu.on_update(lambda _: (setattr(self, "mode", self.mode_menu.value), self.touch()))
        self.camera_menu.on_update(lambda _: self.show_camera(data.cameras[names.index(self.camera_menu.value)]))
        shot.on_click(lambda _: self.screenshot())
        key.on_click(lambda _: self.add_keyframe())
        save.on_click(lambda _: self.save_camera_path())

    def _switch_source(self) -> None:
        self.source = next(s for s in self.data.sources if s.name == self.source_menu.value)
        self.frame_slider.max = max(self.source.count - 1, 1)
        self.frame_slider.value = 0
        self.set_frame(self.source, 0)

    def _people_gui(self) -> None:
        """Person A (whose skeleton the poses go on), person B and the blend of their codes (autoencoder runs)."""
        gui, names = self.client.gui, tuple(p.name for p in self.data.people)
        with gui.add_folder("Person"):
            first = gui.add_dropdown("person A", names, initial_value=names[0])
            second = gui.add_dropdown("person B", names, initial_value=names[0])
            blend = gui.add_slider("blend A -> B", 0.0, 1.0, 0.05, 0.0)

        def choose(_):
            self.person, self.other = names.index(first.value), names.index(second.value)
            self.set_frame(self.source, self.index)

        first.on_update(choose)
        second.on_update(choose)
        blend.on_update(lambda _: (setattr(self, "blend", float(blend.value)), self.touch()))

    def _toggle_play(self) -> None:
        self.playing = not self.playing
        self._play_started, self._play_from = time.monotonic(), self.index
        self.wake.set()

    def _set_speed(self, speed: float) -> None:
        """A new playback speed, continuing from the frame shown (not jumping to where it would have been)."""
        self.speed = float(speed)
        self._play_started, self._play_from = time.monotonic(), self.index

    def _scale_bones(self, name: str, value: float) -> None:
        self.pose.bone_scales[name] = float(value)
        self._place_handles()
        self.touch()

    def _place_handles(self) -> None:
        """Show (or hide) a rotation handle at every joint, oriented as the joint."""
        if not self.hand_box.value:
            for handle in self.handles:
                handle.remove()
            self.handles = []
            return
        world = self.pose.world_from_joint()
        if not self.handles:
            for j, name in enumerate(JOINT_NAMES):
                handle = self.client.scene.add_transform_controls(
                    f"/joints/{name}", scale=0.12, disable_axes=True, disable_sliders=True, depth_test=False
                )
                handle.on_update(lambda _, j=j, h=handle: self._turn(j, h))
                self.handles.append(handle)
        for j, handle in enumerate(self.handles):
            handle.position = world[j, :3, 3]
            x, y, z, w = Rotation.from_matrix(world[j, :3, :3]).as_quat()
            handle.wxyz = (w, x, y, z)

    def _turn(self, joint: int, handle) -> None:
        w, x, y, z = handle.wxyz
        self.pose.rotate_joint(joint, Rotation.from_quat([x, y, z, w]).as_matrix())
        self._place_handles()
        self.touch()

    # --- outputs -----------------------------------------------------------------------------------------------
    def screenshot(self) -> Path:
        """Render the current view at full size, save it under the run's ``viewer/`` folder and send it to the tab."""
        camera = self.current_camera(self.data.full)
        render = self.render(camera)
        while render is None and not self.stop.is_set():  # the view changed under it: take the newer one
            render = self.render(self.current_camera(self.data.full))
        image = self.picture(render)
        ok, png = cv2.imencode(".png", cv2.cvtColor(image, cv2.COLOR_RGB2BGR))
        path = _unique(self.data.out_dir / "screenshots", "screenshot", ".png")
        if not ok:  # OpenCV answers False rather than raising
            raise OSError(errno.EIO, "the screenshot could not be encoded as PNG", str(path))
        atomic_write_bytes(path, png.tobytes())
        self.client.send_file_download(path.name, png.tobytes())
        return path

    def add_keyframe(self) -> None:
        camera = self.current_camera(self.data.full)
        fov = float(np.degrees(self.client.camera.fov))
        frame = self.index if self.source is self.data.sources[0] and not self.data.people else 0
        self.keyframes.append(Keyframe(camera.cam_from_world, fov, frame))
        self.client.add_notification("camera path", f"{len(self.keyframes)} keyframes", auto_close_seconds=2.0)

    def save_camera_path(self) -> Path | None:
        """Write the keyframes (the current camera alone if none were added) for narf-render-video --camera-path."""
        if not self.keyframes:
            self.add_keyframe()
        camera = self.current_camera(self.data.full)
        text = json.dumps(CameraPath(camera.width, camera.height, self.keyframes).to_json(), indent=1).encode()
        path = _unique(self.data.out_dir / "camera_paths", "path", ".json")
        atomic_write_bytes(path, text)
        self.client.send_file_download(path.name, text)
        self.client.add_notification("camera path saved", str(path), auto_close_seconds=5.0)
        return path

    def close(self) -> None:
        self.stop.set()
        self.wake.set()


def _unique(folder: Path, stem: str, suffix: str) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    stamp = time.strftime("%Y%m%d-%H%M%S")
    path, k = folder / f"{stem}-{stamp}{suffix}", 1
    while path.exists():
        path, k = folder / f"{stem}-{stamp}-{k}{suffix}", k + 1
    return path


class Viewer:
    """The viser server and its tabs."""

    def __init__(self, data: ViewerData, host: str = "127.0.0.1", port: int = 8080):
        self.data, self.sessions, self.threads = data, {}, []
        self.server = viser.ViserServer(host=host, port=port, verbose=False)
        self.server.scene.set_up_direction(tuple(data.up))
        self.server.on_client_connect(self._connect)
        self.server.on_client_disconnect(self._disconnect)

    def _connect(self, client: viser.ClientHandle) -> None:
        session = Session(self.data, client)
        self.sessions[client.client_id] = session
        self.threads = [t for t in self.threads if t.is_alive()] + [session.thread]

    def _disconnect(self, client: viser.ClientHandle) -> None:
        session = self.sessions.pop(client.client_id, None)
        if session is not None:
            session.close()

    def stop(self) -> None:
        """Close every tab and wait for the render threads (a thread still inside torch when the interpreter exits
        aborts the process)."""
        for session in list(self.sessions.values()):
            session.close()
        self.sessions.clear()
        for thread in self.threads:
            thread.join(timeout=30)
        self.server.stop()


def viewer_data(
    run_dir: Path | SavedRun, motion: Path | None, device: str, preview: int, full: int, motion_fps: float | None = None
) -> ViewerData:
    """A subject run: its capture's frames (and ``motion``, placed on its stage) on the subject's skeleton, the
    training cameras then the held-out ones as presets, the floor's (or the cameras') up axis."""
    from pipelines.runs.requests import MotionClip
    from pipelines.runs.subject.session import load_run
    from pipelines.runs.subject.video import motion_params

    run = load_run(run_dir, device)  # a folder, or its checkpoint already read
    capture, body_model = run.capture, run.body_model

    @lru_cache(maxsize=8)
    def rest_joints(shapes: bytes) -> np.ndarray:  # the rest skeleton of a shape, computed once per shape
        betas = torch.tensor(np.frombuffer(shapes, np.float32), dtype=body_model.dtype)[None]
        return body_model.rest_joints(betas)[0].double().numpy()

    def on_skeleton(params) -> AvatarPose:
        return AvatarPose.from_params(params, rest_joints(np.asarray(params.shapes, np.float32).tobytes()))

    sources = [PoseSource("capture frames", capture.n_frames, 30.0, lambda k: on_skeleton(run.params(k)))]
    if motion is not None:
        params, report = motion_params(run, MotionClip(Path(motion), source_fps=motion_fps))
        sources.append(
            PoseSource(
                f"motion: {Path(motion).name}", len(params), float(report["fps"]), lambda k: on_skeleton(params[k])
            )
        )
    views = list(run.protocol.train_views) + [v for v in run.protocol.test_views if v not in run.protocol.train_views]
    cameras = [capture.cameras[v].undistorted().scaled(capture.ratio) for v in views]
    up = capture.floor.up if capture.floor is not None else camera_up(capture.cameras)
    out = run_folder(run_dir) / "viewer"
    return ViewerData(
        run.field,
        run.config,
        sources,
        cameras,
        np.asarray(up, np.float64),
        device,
        out,
        [],
        preview,
        full,
        colour=run.colour_poses,  # an edited pose is no capture frame: nearest-place colour (docs/model.md §4)
    )


def autoencoder_viewer_data(
    run_dir: Path | SavedRun, device: str, preview: int, full: int, n_people: int = 16
) -> ViewerData:
    """An autoencoder run: up to ``n_people`` people of its set (evenly spread over the meshes, held-out ones
    included), each encoded from its second-view render; the poses are theirs, put on the chosen person's skeleton;
    the presets are their render cameras; up is the first person's pelvis-to-neck direction."""
    from fitting.autoencoder import encode
    from fitting.evaluate import spread
    from pipelines.runs.autoencoder.evaluation import load_autoencoder_run
    from pipelines.runs.autoencoder.session import load_views

    run = load_autoencoder_run(run_dir, device)  # a folder, or its checkpoint already read
    meshes = spread(list(range(run.dataset.n_meshes)), n_people)
    views, inputs, poses = load_views(run.dataset, "same_view", meshes, progress=False)
    with torch.no_grad():
        codes = encode(run.encoder, inputs.to(device)).cpu()
    joints = poses.world_from_joint.double().numpy()
    people = []
    for k, mesh in enumerate(meshes):
        held = "" if mesh < run.dataset.n_train_meshes else " (held out)"
        rest = AvatarPose.from_joints(joints[k]).rest
        people.append(Person(f"person {mesh}{held}", codes[k : k + 1], rest, views[k].camera))
    source = PoseSource("the people's poses", len(meshes), 2.0, lambda k: AvatarPose.from_joints(joints[k]))
    up = joints[0, 12, :3, 3] - joints[0, 0, :3, 3]
    out = run_folder(run_dir) / "viewer"
    cameras = [replace(p.camera, name=p.name) for p in people]
    return ViewerData(
        run.field, run.config, [source], cameras, up / np.linalg.norm(up), device, out, people, preview, full
    )

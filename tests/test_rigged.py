"""Rigged glTF export: the writer against the glTF 2.0 rules (read back with pygltflib), linear blend skinning of
the written file, the export of a fitted run, and (where installed) Blender's importer."""

import json
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from pipelines.datasets.gltf import Animation, Skeleton, SkinnedMesh, skinned_glb

pygltflib = pytest.importorskip("pygltflib", reason="pygltflib is in the test extra (pip install -e '.[test]')")


def _read(path_or_bytes):
    gltf = pygltflib.GLTF2.load_from_bytes(path_or_bytes) if isinstance(path_or_bytes, bytes) else None
    gltf = gltf or pygltflib.GLTF2().load(str(path_or_bytes))
    blob = gltf.binary_blob()
    dtypes = {5126: np.float32, 5123: np.uint16, 5125: np.uint32}
    widths = {"SCALAR": 1, "VEC3": 3, "VEC4": 4, "MAT4": 16}

    def accessor(index):
        a = gltf.accessors[index]
        view = gltf.bufferViews[a.bufferView]
        assert view.byteOffset % 4 == 0 and a.byteOffset in (None, 0)
        values = np.frombuffer(blob, dtypes[a.componentType], a.count * widths[a.type], view.byteOffset)
        return values.reshape(a.count, widths[a.type]) if widths[a.type] > 1 else values

    return gltf, accessor


def _matrix(translation, quaternion):
    out = np.eye(4)
    out[:3, :3] = Rotation.from_quat(quaternion).as_matrix()
    out[:3, 3] = translation
    return out


def _posed_globals(gltf, accessor, frame: int) -> np.ndarray:
    """Each joint node's global transform at animation frame ``frame``, chained through the node hierarchy."""
    local = {j: _matrix(n.translation, n.rotation) for j, n in enumerate(gltf.nodes) if n.mesh is None}
    animation = gltf.animations[0]
    for channel in animation.channels:
        values = accessor(animation.samplers[channel.sampler].output)[frame]
        node = channel.target.node
        t, q = local[node][:3, 3].copy(), Rotation.from_matrix(local[node][:3, :3]).as_quat()
        local[node] = _matrix(values if channel.target.path == "translation" else t, values if len(values) == 4 else q)
    parent = {c: j for j, n in enumerate(gltf.nodes) for c in (n.children or [])}

    def chained(j):
        return local[j] if j not in parent else chained(parent[j]) @ local[j]

    return np.stack([chained(j) for j in sorted(local)])


def _chain_skeleton():
    """Three joints in a row along x (root at the origin), bind = rest (identity rotations)."""
    bind = np.tile(np.eye(4), (3, 1, 1))
    bind[:, 0, 3] = [0.0, 1.0, 2.0]
    return Skeleton(("root", "middle", "tip"), (-1, 0, 1), bind)


def test_skinned_glb_follows_the_specification_and_skins_linearly():
    skeleton = _chain_skeleton()
    rng = np.random.default_rng(0)
    vertices = rng.uniform(-0.2, 2.2, (40, 3))
    faces = rng.integers(0, 40, (30, 3))
    joints = np.tile([0, 1, 2, 0], (40, 1)).astype(np.uint16)
    weights = rng.dirichlet([1, 1, 1], 40)
    weights = np.concatenate([weights, np.zeros((40, 1))], axis=1).astype(np.float32)
    # an animation: the root travels and turns, the middle joint bends about z by up to 90 degrees
    times = np.arange(5) / 30.0
    world = np.zeros((5, 3, 4, 4))
    for t in range(5):
        root = _matrix([0.1 * t, 0, 0], Rotation.from_euler("y", 10 * t, degrees=True).as_quat())
        bend = _matrix([1.0, 0, 0], Rotation.from_euler("z", 22.5 * t, degrees=True).as_quat())
        world[t] = [root, root @ bend, root @ bend @ _matrix([1.0, 0, 0], [0, 0, 0, 1])]
    colours = rng.uniform(0, 1, (40, 3))
    mesh = SkinnedMesh(vertices, np.tile([0, 0, 1.0], (40, 1)), faces, colours, joints, weights)
    data = skinned_glb(mesh, skeleton, Animation(times, world))
    assert data[:4] == b"glTF" and int.from_bytes(data[8:12], "little") == len(data) and len(data) % 4 == 0
    gltf, accessor = _read(data)
    primitive = gltf.meshes[0].primitives[0]
    position = gltf.accessors[primitive.attributes.POSITION]
    # POSITION and the animation's input need min / max (docs/formats.md §10); float32 in the file
    np.testing.assert_allclose(position.min, vertices.min(0), rtol=1e-6)
    assert gltf.accessors[gltf.animations[0].samplers[0].input].max == [pytest.approx(4 / 30)]
    assert [n.name for n in gltf.nodes[:3]] == ["root", "middle", "tip"] and gltf.skins[0].joints == [0, 1, 2]
    np.testing.assert_allclose(accessor(primitive.attributes.WEIGHTS_0).sum(1), 1, atol=1e-6)
    # COLOR_0 is linear: sRGB 0.5 is 0.214 linear
    linear = accessor(primitive.attributes.COLOR_0)
    np.testing.assert_allclose(
        linear, np.where(colours <= 0.04045, colours / 12.92, ((colours + 0.055) / 1.055) ** 2.4), rtol=1e-6
    )
    ibm = accessor(gltf.skins[0].inverseBindMatrices).reshape(-1, 4, 4).transpose(0, 2, 1)
    for t in (0, 2, 4):
        posed = _posed_globals(gltf, accessor, t)
        # the node chain reproduces the global transforms the animation was made from (float32 file: ~1e-6)
        np.testing.assert_allclose(posed, world[t], atol=1e-5)
        skinning = np.einsum("vk,vkij->vij", accessor(primitive.attributes.WEIGHTS_0), (posed @ ibm)[joints])
        skinned = np.einsum("vij,vj->vi", skinning, np.c_[vertices, np.ones(40)])[:, :3]
        expected = sum(
            weights[:, k, None]
            * (np.c_[vertices, np.ones(40)] @ (world[t, k] @ np.linalg.inv(skeleton.bind[k])).T)[:, :3]
            for k in range(3)
        )
        np.testing.assert_allclose(skinned, expected, atol=1e-5)
    scene = trimesh.load(trimesh.util.wrap_as_stream(data), file_type="glb")
    assert len(scene.geometry) == 1


def test_skinned_glb_refuses_a_bad_skeleton():
    skeleton = _chain_skeleton()
    mesh = SkinnedMesh(
        np.zeros((3, 3)),
        np.zeros((3, 3)),
        np.array([[0, 1, 2]]),
        np.zeros((3, 3)),
        np.zeros((3, 4), np.uint16),
        np.ones((3, 4), np.float32) / 4,
    )
    with pytest.raises(ValueError, match="parent must come before"):
        skinned_glb(mesh, Skeleton(skeleton.names, (-1, 2, 0), skeleton.bind))


def _kabsch_residual(source: np.ndarray, target: np.ndarray) -> tuple[float, np.ndarray]:
    """The largest distance left after the best rigid map of ``source`` (N, 3) onto ``target``, and its rotation."""
    a, b = source - source.mean(0), target - target.mean(0)
    u, _, vt = np.linalg.svd(a.T @ b)
    d = np.sign(np.linalg.det(u @ vt))
    rotation = (u @ np.diag([1, 1, d]) @ vt).T
    return float(np.abs(a @ rotation.T - b).max()), rotation


@pytest.fixture(scope="module")
def rigged(tiny_run, data_root_64, tmp_path_factory):
    """The tiny run exported with --rigged and three frames of its capture's motion at 10 fps."""
    from pipelines.cli import export_mesh as cli_export
    from pipelines.cli.common import run_cli

    motion = data_root_64 / "synthetic" / "taichi" / "new_params"
    out = tmp_path_factory.mktemp("rigged") / "avatar.glb"
    args = ["--run", str(tiny_run), "--rigged", "--resolution", "24", "--quiet", "--out", str(out)]
    assert (
        run_cli("narf-export-mesh", cli_export.main, [*args, "--motion", str(motion), "--frames", "2:5", "--fps", "10"])
        == 0
    )
    return out, motion


def test_rigged_export_of_a_fitted_run(rigged, tiny_run, tmp_path, capsys):
    import torch

    from narf.kinematics import JOINT_NAMES
    from pipelines.cli import export_mesh as cli_export
    from pipelines.cli.common import run_cli
    from pipelines.datasets.floor import camera_up
    from pipelines.runs.requests import MotionClip
    from pipelines.runs.subject.session import load_run
    from pipelines.runs.subject.video import motion_params

    out, motion = rigged
    gltf, accessor = _read(out)
    assert [n.name for n in gltf.nodes[:24]] == list(JOINT_NAMES) and len(gltf.skins[0].joints) == 24
    primitive = gltf.meshes[0].primitives[0]
    assert primitive.attributes.COLOR_0 is not None
    np.testing.assert_allclose(accessor(primitive.attributes.WEIGHTS_0).sum(1), 1, atol=1e-6)
    np.testing.assert_allclose(accessor(gltf.animations[0].samplers[0].input), [0, 0.1, 0.2], atol=1e-7)
    # the animated joints are the body model's joints of the motion as placed on the capture's stage (as for
    # videos), up to one rigid map (the export frame) that takes the capture's up to glTF's +y
    run = load_run(tiny_run)
    params, _ = motion_params(run, MotionClip(motion, start=2, frames=3, fps=10.0))
    stack = [torch.as_tensor(np.stack([getattr(p, key) for p in params])) for key in ("poses", "rh", "th", "shapes")]
    with torch.no_grad():
        expected = run.body_model.pose_zju(*stack).world_from_joint[..., :3, 3].double().numpy()
    posed = np.stack([_posed_globals(gltf, accessor, t)[:, :3, 3] for t in range(3)])
    residual, rotation = _kabsch_residual(expected.reshape(-1, 3), posed.reshape(-1, 3))
    # float32 file values of metre-sized numbers, through a chain of up to 8 joints: ~1e-6
    assert residual < 1e-4
    np.testing.assert_allclose(rotation @ camera_up(run.capture.cameras), [0, 1, 0], atol=0.05)
    args = ["--run", str(tiny_run), "--rigged", "--quiet", "--out", str(tmp_path / "a.ply")]
    assert run_cli("narf-export-mesh", cli_export.main, args) == 2
    assert "name it .glb" in capsys.readouterr().err


# Debian's Blender 3.4 importer still writes np.bool, which Debian's numpy 1.24 removed: the alias is put back
BLENDER_CHECK = """
import bpy, json, sys
import numpy
numpy.bool = bool
bpy.ops.wm.read_factory_settings(use_empty=True)
bpy.ops.import_scene.gltf(filepath=sys.argv[-1])
armatures = [o for o in bpy.data.objects if o.type == "ARMATURE"]
meshes = [o for o in bpy.data.objects if o.type == "MESH"]
mesh = meshes[0]
print("BLENDER" + json.dumps({
    "armatures": len(armatures),
    "bones": len(armatures[0].data.bones),
    "meshes": len(meshes),
    "vertices": len(mesh.data.vertices),
    "colour_attributes": [a.name for a in mesh.data.color_attributes],
    "vertex_groups": len(mesh.vertex_groups),
    "armature_modifier": any(m.type == "ARMATURE" and m.object == armatures[0] for m in mesh.modifiers),
    "keyframes": sorted({len(c.keyframe_points) for a in bpy.data.actions for c in a.fcurves}),
}))
"""


def blender_report(glb) -> dict:
    """What Blender's glTF importer makes of a file (Blender run in the background)."""
    result = subprocess.run(
        ["blender", "--background", "--factory-startup", "--python-expr", BLENDER_CHECK, "--", str(glb)],
        capture_output=True,
        text=True,
        timeout=300,
    )
    lines = [line for line in result.stdout.splitlines() if line.startswith("BLENDER{")]
    assert lines, result.stdout[-2000:] + result.stderr[-2000:]
    return json.loads(lines[-1][len("BLENDER") :])


@pytest.mark.skipif(shutil.which("blender") is None, reason="Blender is not installed (apt-get install blender)")
def test_blender_imports_the_rigged_export(rigged):
    report = blender_report(rigged[0])
    # one armature of the 24 SMPL joints, one skinned mesh with its colours, and the three animation frames
    assert report["armatures"] == 1 and report["bones"] == 24 and report["meshes"] == 1
    assert report["colour_attributes"] and report["armature_modifier"] and report["vertex_groups"] >= 19
    assert report["keyframes"] == [3]


def test_exported_files_get_the_usual_permissions(tmp_path):
    import os

    from fitting.files import atomic_write_bytes

    mask = os.umask(0o022)
    os.umask(mask)
    atomic_write_bytes(tmp_path / "a.glb", b"x")
    # a file written through a temporary one is as readable as any new file (0666 less the umask), not 0600
    assert (tmp_path / "a.glb").stat().st_mode & 0o777 == 0o666 & ~mask


THREE = Path(__file__).resolve().parents[1] / ".cache" / "three" / "package"
THREE_PAGE = """<!doctype html><html><body><script type="importmap">
{"imports": {"three": "./build/three.module.js", "three/addons/": "./examples/jsm/"}}
</script><script type="module">
import * as THREE from "three";
import { GLTFLoader } from "three/addons/loaders/GLTFLoader.js";
new GLTFLoader().load("avatar.glb", (gltf) => {
  const skinned = [];
  gltf.scene.traverse((o) => { if (o.isSkinnedMesh) skinned.push(o); });
  const mesh = skinned[0];
  const mixer = new THREE.AnimationMixer(gltf.scene);
  const clip = gltf.animations[0];
  mixer.clipAction(clip).play();
  const box = (t) => { mixer.setTime(t); gltf.scene.updateMatrixWorld(true);
    const b = new THREE.Box3(); const v = new THREE.Vector3();
    for (let i = 0; i < mesh.geometry.attributes.position.count; i += 50) {
      mesh.getVertexPosition(i, v); v.applyMatrix4(mesh.matrixWorld); b.expandByPoint(v); }
    return [b.min.toArray(), b.max.toArray()]; };
  window.result = {skinned: skinned.length, bones: mesh.skeleton.bones.length,
    names: mesh.skeleton.bones.map((b) => b.name), colours: !!mesh.geometry.attributes.color,
    duration: clip.duration, tracks: clip.tracks.length, start: box(0), later: box(0.99 * clip.duration)};
}, undefined, (e) => { window.result = {error: String(e)}; });
</script></body></html>"""


@pytest.mark.skipif(
    not (THREE / "build" / "three.module.js").is_file(),
    reason="three.js is not in .cache/three "
    "(curl -sS https://registry.npmjs.org/three/-/three-0.170.0.tgz | tar -xz -C .cache/three)",
)
def test_threejs_loads_and_plays_the_rigged_export(rigged, tmp_path):
    import functools
    import http.server
    import threading

    import browser

    if browser.CHROMIUM is None or browser.CHROMEDRIVER is None:
        pytest.skip(browser.MISSING)
    site = tmp_path / "site"
    shutil.copytree(THREE, site, ignore=shutil.ignore_patterns("src", "*.cjs", "*.min.js", "*webgpu*"))
    shutil.copy(rigged[0], site / "avatar.glb")
    (site / "index.html").write_text(THREE_PAGE)
    handler = functools.partial(http.server.SimpleHTTPRequestHandler, directory=str(site))
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    driver = browser.chromium()
    try:
        driver.get(f"http://127.0.0.1:{server.server_address[1]}/index.html")
        result = browser.wait(lambda: driver.execute_script("return window.result || null"), 60, "GLTFLoader")
    finally:
        driver.quit()
        server.shutdown()
    assert "error" not in result, result
    from narf.kinematics import JOINT_NAMES

    # one skinned mesh on the 24 named joints, its colours, and 24 joints x (rotation, translation) tracks over the
    # three frames at 10 fps (0.2 s); the posed mesh moves from the first frame to
    # near the last (at the clip's duration a repeating clip wraps to its start)
    assert result["skinned"] == 1 and result["bones"] == 24 and result["names"] == list(JOINT_NAMES)
    assert result["colours"] and result["tracks"] == 48 and result["duration"] == pytest.approx(0.2)
    assert result["start"] != result["later"]


VALIDATOR = Path(__file__).resolve().parents[1] / ".cache" / "gltf-validator" / "package" / "index.js"
VALIDATE = """
const validator = require(process.argv[1]);
const data = new Uint8Array(require("fs").readFileSync(process.argv[2]));
validator.validateBytes(data).then((report) => console.log(JSON.stringify(report.issues)), (e) => {
  console.log(JSON.stringify({error: String(e)}));
});
"""


@pytest.mark.skipif(
    shutil.which("node") is None or not VALIDATOR.is_file(),
    reason="node or the Khronos glTF Validator is missing (apt-get install nodejs; curl -sS "
    "https://registry.npmjs.org/gltf-validator/-/gltf-validator-2.0.0-dev.3.10.tgz | tar -xz -C .cache/gltf-validator)",
)
def test_khronos_validator_finds_no_issue(rigged):
    done = subprocess.run(
        ["node", "-e", VALIDATE, str(VALIDATOR), str(rigged[0])], capture_output=True, text=True, timeout=120
    )
    findings = json.loads(done.stdout.strip().splitlines()[-1])
    # no errors, and no warnings, infos or hints either (unused data, non-unit quaternions, unsorted times, ...)
    assert findings.get("numErrors") == 0, findings
    assert (findings["numWarnings"], findings["numInfos"], findings["numHints"]) == (0, 0, 0), findings["messages"]

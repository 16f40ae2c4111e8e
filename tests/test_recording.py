"""Rollout recordings: record scripted episodes to an .rrd and read them back with rerun's API."""

from __future__ import annotations

import sys

import numpy as np
import pytest

rr = pytest.importorskip("rerun")
from rerun.chunk import RrdReader  # noqa: E402

from heml_gym.agents.recording import REWARD_ENTITIES, REWARD_TERMS, SCALAR_ENTITIES, record_rollouts  # noqa: E402
from heml_gym.envs.core import TaskSettings  # noqa: E402
from heml_gym.envs.scripted import scripted_policy  # noqa: E402
from heml_gym.envs.tissue_retraction import TissueRetractionEnv  # noqa: E402

MAX_STEPS = 8
EPISODES = 2
SEED = 3


def _env():
    return TissueRetractionEnv(settings=TaskSettings(max_steps=MAX_STEPS))


def _replay(episodes: int, seed: int):
    """The same rollouts, played without recording: per frame the info of reset / step."""
    env, policy = _env(), scripted_policy("TissueRetraction")
    frames, rewards, lengths = [], [], []
    for k in range(episodes):
        obs, info = env.reset(seed=seed + k)
        policy.reset()
        frames.append(info)
        done, n = False, 0
        while not done:
            obs, reward, terminated, truncated, info = env.step(policy(obs))
            frames.append(info)
            rewards.append((reward, info))
            done, n = terminated or truncated, n + 1
        lengths.append(n)
    return frames, rewards, lengths


def _temporal(store) -> dict[str, dict[str, list]]:
    """Per entity path, the columns of its temporal rows (all chunks), sorted by ``step``."""
    out: dict[str, dict[str, list]] = {}
    for chunk in store.stream().to_chunks():
        if chunk.is_static:
            continue
        batch = chunk.to_record_batch()
        cols = out.setdefault(chunk.entity_path, {})
        before = len(cols["step"]) if "step" in cols else 0
        names = [n for n in batch.schema.names if n != "rerun.controls.RowId"]
        for name in names:
            column = batch.column(name)
            if name == "sim_time":  # duration[ns]
                column = column.cast("int64")
            cols.setdefault(name, [None] * before).extend(column.to_pylist())
        for name in cols:  # columns this chunk does not have: empty for its rows
            if name not in names:
                cols[name].extend([None] * batch.num_rows)
    for cols in out.values():
        order = np.argsort(cols["step"], kind="stable")
        for name in cols:
            cols[name] = [cols[name][i] for i in order]
    return out


def _static(store) -> dict[str, dict[str, list]]:
    out: dict[str, dict[str, list]] = {}
    for chunk in store.stream().to_chunks():
        if chunk.is_static:
            batch = chunk.to_record_batch()
            cols = out.setdefault(chunk.entity_path, {})
            for name in batch.schema.names:
                cols.setdefault(name, []).extend(batch.column(name).to_pylist())
    return out


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    path = tmp_path_factory.mktemp("rec") / "rollout.rrd"
    env = _env()
    summary = record_rollouts(env, scripted_policy("TissueRetraction"), path=path, episodes=EPISODES,
                              seed=SEED)
    return path, summary, env


def test_summary_matches_an_independent_replay(recording):
    path, summary, _ = recording
    frames, _, lengths = _replay(EPISODES, SEED)
    assert summary["episodes"] == EPISODES
    assert summary["episode_lengths"] == lengths
    assert summary["steps"] == sum(lengths)
    assert summary["frames"] == len(frames) == sum(lengths) + EPISODES
    assert summary["path"] == str(path)
    assert 0.0 <= summary["success_rate"] <= 1.0


def test_rrd_layout_and_frames(recording):
    path, summary, env = recording
    assert path.is_file() and path.stat().st_size > 0

    reader = RrdReader(path)
    (entry,) = reader.recordings()
    assert entry.recording_id == summary["recording_id"]
    assert entry.application_id == "heml_gym"
    # the blueprint: a 3D view and the camera view beside 6 time-series views and the episode log
    (bp_entry,) = reader.blueprints()
    bp_paths = reader.stream(store=bp_entry).collect().schema().entity_paths()
    assert sum(1 for p in bp_paths if p.startswith("/view/") and p.count("/") == 2) == 9

    store = reader.stream().collect()
    schema = store.schema()
    paths = set(schema.entity_paths())
    world = {"/world/tissue", "/world/gripper", "/world/target", "/world/held", "/world/grasp_force",
             "/world/camera", "/world/camera/image", "/world/camera/depth", "/world/support", "/plots/outcome"}
    scalars = {"/" + e for e in SCALAR_ENTITIES}
    assert world | scalars | {"/log/episodes"} <= paths
    index = {c.name for c in schema.index_columns()}
    assert {"step", "sim_time", "episode", "episode_step"} <= index
    for entity, archetype in [("/world/tissue", "Mesh3D"), ("/world/gripper", "Boxes3D"),
                              ("/world/target", "Points3D"), ("/world/camera", "Pinhole"),
                              ("/world/camera/image", "Image"), ("/world/camera/depth", "DepthImage")]:
        assert schema.column_names_for(entity_path=entity, archetype=archetype)

    n_frames, n_steps = summary["frames"], summary["steps"]
    frames, rewards, lengths = _replay(EPISODES, SEED)
    data = _temporal(store)

    # one mesh row per frame, on consecutive steps; sim_time = step * control_dt
    mesh = data["/world/tissue"]
    assert mesh["step"] == list(range(n_frames)) == list(range(len(frames)))
    dt_ns = round(env.unwrapped.task.settings.control_dt * 1e9)
    assert mesh["sim_time"] == [s * dt_ns for s in mesh["step"]]
    expected_episode = [k for k, n in enumerate(lengths) for _ in range(n + 1)]
    expected_episode_step = [i for n in lengths for i in range(n + 1)]
    assert mesh["episode"] == expected_episode
    assert mesh["episode_step"] == expected_episode_step

    # the mesh: the scene's surface triangles, flat-shaded (three own vertices each)
    task = env.unwrapped.task
    faces = task.scene.surface_faces
    assert all(len(v) == 3 * len(faces) for v in mesh["Mesh3D:vertex_positions"])
    assert all(len(c) == 3 * len(faces) for c in mesh["Mesh3D:vertex_colors"])
    (triangles,) = _static(store)["/world/tissue"]["Mesh3D:triangle_indices"]
    np.testing.assert_array_equal(np.array(triangles), np.arange(3 * len(faces)).reshape(-1, 3))
    # the last frame's positions are the env's final state (recorded as float32)
    np.testing.assert_allclose(np.array(mesh["Mesh3D:vertex_positions"][-1]), task.x[0][faces].reshape(-1, 3),
                               atol=1e-6)
    # the normals are the faces' own: perpendicular to the triangle's edges
    tri = np.array(mesh["Mesh3D:vertex_positions"][-1]).reshape(-1, 3, 3)
    normals = np.array(mesh["Mesh3D:vertex_normals"][-1]).reshape(-1, 3, 3)
    assert np.abs((normals[:, 0] * (tri[:, 1] - tri[:, 0])).sum(axis=1)).max() < 1e-5
    # the camera image is the env's own view of that frame: the last one equals the env's
    # render of its final state, colour and depth
    from heml_gym.agents.recording import CAMERA_SIZE

    image = data["/world/camera/image"]
    assert image["step"] == list(range(n_frames))
    view = env.unwrapped.camera_view(0, CAMERA_SIZE)
    recorded = np.frombuffer(bytes(image["Image:buffer"][-1][0]), dtype=np.uint8).reshape(view["rgb"].shape)
    np.testing.assert_array_equal(recorded, view["rgb"])
    depth = data["/world/camera/depth"]
    recorded_depth = np.frombuffer(bytes(depth["DepthImage:buffer"][-1][0]), dtype=view["depth"].dtype)
    np.testing.assert_array_equal(recorded_depth.reshape(view["depth"].shape), view["depth"])

    for entity in ("/world/gripper", "/world/target", "/world/held"):
        assert data[entity]["step"] == list(range(n_frames))

    # scalar series: one value per frame (measurements) or per step (rewards), equal to
    # the values of the independent replay
    step_frames = [s for s, i in zip(range(n_frames), expected_episode_step) if i > 0]
    for entity, every_frame in SCALAR_ENTITIES.items():
        series = data["/" + entity]
        assert series["step"] == (list(range(n_frames)) if every_frame else step_frames), entity
        assert all(len(v) == 1 for v in series["Scalars:scalars"]), entity
        assert len(series["Scalars:scalars"]) == (n_frames if every_frame else n_steps)
    values = {e: np.array(data["/" + e]["Scalars:scalars"])[:, 0] for e in SCALAR_ENTITIES}
    np.testing.assert_allclose(values["plots/exposure/exposure"], [f["exposure"] for f in frames])
    np.testing.assert_allclose(values["plots/strain/max_strain"], [f["max_strain"] for f in frames])
    np.testing.assert_allclose(values["plots/grasp_force"], [f["grasp_force"] for f in frames])
    np.testing.assert_allclose(values[REWARD_ENTITIES["total"]], [r for r, _ in rewards])
    for term in REWARD_TERMS:
        np.testing.assert_allclose(values[REWARD_ENTITIES[term]], [i[f"reward_{term}"] for _, i in rewards])
    # one outcome marker per episode, at its last frame
    outcome = data["/plots/outcome"]
    ends = list(np.cumsum([n + 1 for n in lengths]) - 1)
    assert outcome["step"] == ends

    # episode boundaries: a start and an end line per episode
    log = data["/log/episodes"]
    texts = [t for row in log["TextLog:text"] for t in row]  # one text per row
    assert len(texts) == 2 * EPISODES
    assert [t.split(":")[0] for t in texts] == [f"episode {k} {w}" for k in range(EPISODES)
                                                for w in ("start", "end")]
    for k in range(EPISODES):
        assert summary["outcomes"][k] in texts[2 * k + 1]


def test_two_recordings_do_not_mix(tmp_path):
    env, policy = _env(), scripted_policy("TissueRetraction")
    a = record_rollouts(env, policy, path=tmp_path / "a.rrd", episodes=1, seed=0)
    b = record_rollouts(env, policy, path=tmp_path / "b.rrd", episodes=1, seed=1)
    assert a["recording_id"] != b["recording_id"]
    for summary in (a, b):
        reader = RrdReader(summary["path"])
        assert [e.recording_id for e in reader.recordings()] == [summary["recording_id"]]
        mesh = _temporal(reader.stream().collect())["/world/tissue"]
        assert len(mesh["step"]) == summary["frames"]


def test_clear_errors(tmp_path, monkeypatch):
    env, policy = _env(), scripted_policy("TissueRetraction")
    with pytest.raises(FileNotFoundError, match="cannot write the rerun recording"):
        record_rollouts(env, policy, path=tmp_path / "missing" / "x.rrd")
    with pytest.raises(IsADirectoryError, match="cannot write the rerun recording"):
        record_rollouts(env, policy, path=tmp_path)
    with pytest.raises(ValueError, match="nothing to record to"):
        record_rollouts(env, policy)
    monkeypatch.setitem(sys.modules, "rerun", None)  # as if rerun-sdk were not installed
    monkeypatch.setitem(sys.modules, "rerun.blueprint", None)
    with pytest.raises(ImportError, match=r"pip install 'heml-gym\[viz\]'"):
        record_rollouts(env, policy, path=tmp_path / "x.rrd")

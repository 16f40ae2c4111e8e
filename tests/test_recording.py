"""Rollout recordings: record scripted episodes to an .rrd and read them back with rerun's API.

What is checked against an independent replay of the same seeded episodes (a fresh env and
policy, no recording): the frames and timelines, episode boundaries (the env's episode
lengths), the target, the camera images (colour, depth and segmentation in 2D entities of
their own, none in the 3D scene), the actions (what the policy returned), the hold timer
and success, the strain colours (the reddest vertex shows the env's gauge strain), and the
blueprint (depth in its own view, plots without legends on a linked time axis).
"""

from __future__ import annotations

import sys

import numpy as np
import pytest

rr = pytest.importorskip("rerun")
from rerun.chunk import RrdReader  # noqa: E402

from heml_gym.agents.recording import (ACTION_NAMES, BLUEPRINT_VIEWS, CAMERA_SIZE, REWARD_TERMS,  # noqa: E402
                                       SERIES, THRESHOLDS, record_rollouts, series_entity)
from heml_gym.envs.camera import JAW_OFFSET, SEGMENT_IDS  # noqa: E402
from heml_gym.envs.core import TaskSettings  # noqa: E402
from heml_gym.envs.palette import STRAINED, TISSUE  # noqa: E402
from heml_gym.envs.scripted import scripted_policy  # noqa: E402
from heml_gym.envs.tissue_retraction import TissueRetractionEnv  # noqa: E402

MAX_STEPS = 30
EPISODES = 2
SEED = 3
#: a short hold, so that the scripted policy succeeds within MAX_STEPS (a success and its hold timer)
HOLD_TIME = 0.3


def _env():
    return TissueRetractionEnv(settings=TaskSettings(max_steps=MAX_STEPS, hold_time=HOLD_TIME))


def _replay(episodes: int, seed: int):
    """The same rollouts, played without recording: per frame the info of reset / step and
    the target's place; per step the reward, its info and the policy's action; the episode
    lengths."""
    env, policy = _env(), scripted_policy("TissueRetraction")
    frames, targets, rewards, actions, lengths = [], [], [], [], []
    for k in range(episodes):
        obs, info = env.reset(seed=seed + k)
        policy.reset()
        frames.append(info)
        targets.append(env.snapshot().target)
        done, n = False, 0
        while not done:
            action = np.array(policy(obs), dtype=np.float64)
            obs, reward, terminated, truncated, info = env.step(action)
            frames.append(info)
            targets.append(env.snapshot().target)
            rewards.append((reward, info))
            actions.append(action)
            done, n = terminated or truncated, n + 1
        lengths.append(n)
    return frames, np.array(targets), rewards, np.array(actions), lengths


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
    frames, _, _, _, lengths = _replay(EPISODES, SEED)
    assert summary["episodes"] == EPISODES
    assert summary["episode_lengths"] == lengths
    assert summary["steps"] == sum(lengths)
    assert summary["frames"] == len(frames) == sum(lengths) + EPISODES
    assert summary["path"] == str(path)
    assert 0.0 <= summary["success_rate"] <= 1.0
    # the settings give the recording a success (with its hold timer) to show
    assert any(summary["successes"]) and lengths[0] < MAX_STEPS


@pytest.fixture(scope="module")
def replay():
    return _replay(EPISODES, SEED)


@pytest.fixture(scope="module")
def store(recording):
    path, summary, _ = recording
    reader = RrdReader(path)
    (entry,) = reader.recordings()
    assert entry.recording_id == summary["recording_id"]
    assert entry.application_id == "heml_gym"
    return reader.stream().collect()


@pytest.fixture(scope="module")
def data(store):
    return _temporal(store)


def _blueprint_views(path) -> dict[str, dict]:
    """The blueprint's views: display name -> {"class", "origin", "legend", "link", "query"}."""
    reader = RrdReader(path)
    (bp_entry,) = reader.blueprints()
    views: dict[str, dict] = {}
    for chunk in reader.stream(store=bp_entry).collect().stream().to_chunks():
        parts = chunk.entity_path.strip("/").split("/")
        if parts[0] != "view":
            continue
        batch = chunk.to_record_batch()
        view = views.setdefault(parts[1], {})
        for name in batch.schema.names:
            value = batch.column(name).to_pylist()[-1]
            key = {"ViewBlueprint:class_identifier": "class", "ViewBlueprint:space_origin": "origin",
                   "ViewBlueprint:display_name": "name", "PlotLegend:visible": "legend", "TimeAxis:link": "link",
                   "ViewContents:query": "query"}.get(name)
            if key is not None:
                view[key] = value if key == "query" else value[0]
    return {v["name"]: v for v in views.values()}


def test_blueprint_views(recording):
    path, _, _ = recording
    views = _blueprint_views(path)
    assert {n: v["origin"] for n, v in views.items()} == BLUEPRINT_VIEWS
    by_origin = {v["origin"]: v for v in views.values()}
    assert by_origin["world"]["class"] == "3D"
    # colour, depth and segmentation each in a 2D view of their own, outside the 3D scene
    for origin in ("camera/rgb", "camera/depth", "camera/segmentation"):
        assert by_origin[origin]["class"] == "2D"
    plots = [v for v in views.values() if v["class"] == "TimeSeries"]
    assert len(plots) == 7
    for v in plots:  # no legend over the data; time axes linked; the episode markers in every plot
        assert v["legend"] is False and v["link"] == 2  # LinkAxis.LinkToGlobal
        assert "/plots/episode_start" in v["query"]


def test_entities_and_archetypes(store):
    schema = store.schema()
    paths = set(schema.entity_paths())
    expected = {
        ("/world/tissue", "Mesh3D"), ("/world/gripper", "Boxes3D"), ("/world/target", "Points3D"),
        ("/world/held", "Points3D"), ("/world/grasp_force", "Arrows3D"), ("/world/camera", "Pinhole"),
        ("/world/support", "Mesh3D"), ("/camera/rgb", "Image"), ("/camera/depth", "DepthImage"),
        ("/camera/segmentation", "SegmentationImage"), ("/camera/segmentation", "AnnotationContext"),
        ("/status", "TextDocument"), ("/legend", "TextDocument"), ("/legend/strain_scale", "Image"),
        ("/log/episodes", "TextLog"), ("/plots/episode_start", "Scalars"), ("/plots/success/outcome", "Scalars"),
    }
    for entity, archetype in expected:
        assert entity in paths, entity
        assert schema.column_names_for(entity_path=entity, archetype=archetype), (entity, archetype)
    # nothing of the camera's images in the 3D scene: no image, depth image or point cloud
    # under world/camera (the depth is not drawn over the scene)
    assert not [p for p in paths if p.startswith("/world/camera/")]
    index = {c.name for c in schema.index_columns()}
    assert {"step", "sim_time", "episode", "episode_step"} <= index
    # the support is translucent (the target below it stays visible)
    (albedo,) = _static(store)["/world/support"]["Mesh3D:albedo_factor"]
    assert (albedo[0] & 0xFF) < 255  # RGBA packed as 0xRRGGBBAA


def test_frames_timelines_and_mesh(recording, replay, data, store):
    _, summary, env = recording
    frames, _, _, _, lengths = replay
    n_frames = summary["frames"]
    mesh = data["/world/tissue"]
    assert mesh["step"] == list(range(n_frames)) == list(range(len(frames)))
    dt_ns = round(env.unwrapped.task.settings.control_dt * 1e9)
    assert mesh["sim_time"] == [s * dt_ns for s in mesh["step"]]
    # episode boundaries where the env's episodes end
    assert mesh["episode"] == [k for k, n in enumerate(lengths) for _ in range(n + 1)]
    assert mesh["episode_step"] == [i for n in lengths for i in range(n + 1)]

    task = env.unwrapped.task
    faces = task.scene.surface_faces
    assert all(len(v) == 3 * len(faces) for v in mesh["Mesh3D:vertex_positions"])
    assert all(len(c) == 3 * len(faces) for c in mesh["Mesh3D:vertex_colors"])
    (triangles,) = _static(store)["/world/tissue"]["Mesh3D:triangle_indices"]
    np.testing.assert_array_equal(np.array(triangles), np.arange(3 * len(faces)).reshape(-1, 3))
    np.testing.assert_allclose(np.array(mesh["Mesh3D:vertex_positions"][-1]), task.x[0][faces].reshape(-1, 3),
                               atol=1e-6)
    tri = np.array(mesh["Mesh3D:vertex_positions"][-1]).reshape(-1, 3, 3)
    normals = np.array(mesh["Mesh3D:vertex_normals"][-1]).reshape(-1, 3, 3)
    assert np.abs((normals[:, 0] * (tri[:, 1] - tri[:, 0])).sum(axis=1)).max() < 1e-5
    for entity in ("/world/gripper", "/world/target", "/world/held", "/world/grasp_force", "/camera/rgb",
                   "/camera/depth", "/camera/segmentation", "/status"):
        assert data[entity]["step"] == list(range(n_frames)), entity


def test_strain_colours_show_the_gauge_strain(recording, replay, data):
    """The reddest vertex of every frame shows the env's max gauge strain (pale pink 0 to red
    at the damage strain): colours and the strain plot agree."""
    _, _, env = recording
    frames = replay[0]
    damage = env.unwrapped.task.settings.damage_strain
    shown = []
    for colours in data["/world/tissue"]["Mesh3D:vertex_colors"]:
        green = (np.array(colours, dtype=np.uint32) >> 16) & 0xFF  # RGBA packed as 0xRRGGBBAA
        shown.append((TISSUE[1] - green.min()) / (TISSUE[1] - STRAINED[1]) * damage)
    expected = np.minimum([f["max_strain"] for f in frames], damage)
    assert max(expected) > 0.05  # the tissue is strained at all
    np.testing.assert_allclose(shown, expected, atol=damage / (TISSUE[1] - STRAINED[1]))


def test_target_and_camera_images(recording, replay, data):
    _, _, env = recording
    targets = replay[1]
    target = data["/world/target"]
    np.testing.assert_allclose(np.array([p[0] for p in target["Points3D:positions"]]), targets, atol=1e-6)
    radius = env.unwrapped.task.scene.target_radius
    assert all(r == [pytest.approx(radius)] for r in target["Points3D:radii"])
    # the last images are the env's own view of its final state: colour, depth, segmentation
    view = env.unwrapped.camera_view(0, CAMERA_SIZE)
    rgb = np.frombuffer(bytes(data["/camera/rgb"]["Image:buffer"][-1][0]), dtype=np.uint8)
    np.testing.assert_array_equal(rgb.reshape(view["rgb"].shape), view["rgb"])
    depth = np.frombuffer(bytes(data["/camera/depth"]["DepthImage:buffer"][-1][0]), dtype=view["depth"].dtype)
    np.testing.assert_array_equal(depth.reshape(view["depth"].shape), view["depth"])
    seg = np.frombuffer(bytes(data["/camera/segmentation"]["SegmentationImage:buffer"][-1][0]), dtype=np.uint8)
    seg = seg.reshape(view["segmentation"].shape)
    np.testing.assert_array_equal(seg, view["segmentation"])
    assert {SEGMENT_IDS["tissue"], SEGMENT_IDS["target"]} <= set(np.unique(seg))


def test_series_match_the_replay(recording, replay, data):
    """Per episode series (lines not joined across resets): values, actions, hold timer and
    success equal the replay's; the episode markers sit on its resets and ends."""
    _, summary, env = recording
    frames, _, rewards, actions, lengths = replay
    starts = np.concatenate([[0], np.cumsum([n + 1 for n in lengths])[:-1]])  # reset frames

    def by_episode(seq, k, every_frame):
        """Episode k's part of a per-frame (n + 1 values) or per-step (n values) sequence."""
        first = starts[k] if every_frame else starts[k] - k  # k reset frames before it have no step
        return seq[first:first + lengths[k] + (1 if every_frame else 0)]

    step_values = {
        **{f"action_{a}": actions[:, i] for i, a in enumerate(ACTION_NAMES)},
        "reward": [r for r, _ in rewards], "cost": [i["cost"] for _, i in rewards],
        **{f"reward_{t}": [i[f"reward_{t}"] for _, i in rewards] for t in REWARD_TERMS},
    }
    frame_values = {"exposure": [f["exposure"] for f in frames], "max_strain": [f["max_strain"] for f in frames],
                    "hold_time": [f["hold_time"] for f in frames],
                    "is_success": [float(f["is_success"]) for f in frames],
                    "grasp_force": [f["grasp_force"] for f in frames], "damage": [f["damage"] for f in frames]}
    series = {k: v for k, v in SERIES.items() if k != "goal_distance"}  # (a goal task's, not logged here)
    assert set(step_values) | set(frame_values) == set(series)
    for name, (base, every_frame) in series.items():
        truth = np.asarray(frame_values[name] if every_frame else step_values[name], dtype=np.float64)
        for k, n in enumerate(lengths):
            series = data["/" + series_entity(base, k)]
            assert series["episode"] == [k] * len(series["step"]), name
            assert series["episode_step"] == list(range(0 if every_frame else 1, n + 1)), name
            assert series["step"] == list(range(starts[k] + (0 if every_frame else 1), starts[k] + n + 1)), name
            np.testing.assert_allclose(np.array(series["Scalars:scalars"])[:, 0], by_episode(truth, k, every_frame),
                                       err_msg=name)
    # the hold timer runs up to the setting and the success comes after it
    hold = np.array(data["/" + series_entity(SERIES["hold_time"][0], 0)]["Scalars:scalars"])[:, 0]
    success = np.array(data["/" + series_entity(SERIES["is_success"][0], 0)]["Scalars:scalars"])[:, 0]
    assert summary["successes"][0] and success[-1] == 1.0 and success[:-1].max() == 0.0
    assert hold[-1] == pytest.approx(HOLD_TIME)
    st = env.unwrapped.task.settings
    for entity, field in THRESHOLDS.items():
        assert np.array(data["/" + entity]["Scalars:scalars"])[:, 0].tolist() == [getattr(st, field)] * len(frames)
    # episode markers: a start marker on each reset frame, an outcome marker at each end
    assert data["/plots/episode_start"]["step"] == starts.tolist()
    assert data["/plots/success/outcome"]["step"] == (starts + np.array(lengths)).tolist()
    np.testing.assert_allclose(np.array(data["/plots/success/outcome"]["Scalars:scalars"])[:, 0],
                               [1.0 if s else 0.0 for s in summary["successes"]])
    # the status text of each frame says whether it is a success
    texts = [row[0] for row in data["/status"]["TextDocument:text"]]
    assert [("success: yes" in t) for t in texts] == [bool(f["is_success"]) for f in frames]
    assert all(f"episode {k}, step {i}" in texts[starts[k] + i] for k, n in enumerate(lengths) for i in range(n + 1))

    # episode boundaries in the log: a start and an end line per episode
    log = data["/log/episodes"]
    lines = [t for row in log["TextLog:text"] for t in row]
    assert [t.split(":")[0] for t in lines] == [f"episode {k} {w}" for k in range(EPISODES) for w in ("start", "end")]
    for k in range(EPISODES):
        assert summary["outcomes"][k] in lines[2 * k + 1]


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


@pytest.mark.parametrize("env_id", ["heml_gym/BimanualRetraction-v0", "heml_gym/TissueManipulation-v0"])
def test_the_new_tasks_record_every_grasper_and_their_progress(env_id, tmp_path):
    """A scripted episode of each new task records: one jaw box per grasper (two for the
    bimanual task, in the env's places), and a goal task's distance to its goal, each frame
    equal to ``info["goal_distance"]``."""
    import gymnasium as gym

    from heml_gym.envs.scripted import scripted_policy

    env = gym.make(env_id, settings={"max_steps": 12})
    path = tmp_path / "task.rrd"
    summary = record_rollouts(env, scripted_policy(env.unwrapped.scene), path=path, episodes=1, seed=SEED)
    reader = RrdReader(path)
    (entry,) = reader.recordings()
    data = _temporal(reader.stream().collect())
    centers = data["/world/gripper"]["Boxes3D:centers"][-1]
    assert len(centers) == len(env.unwrapped.task.instruments)
    np.testing.assert_allclose(np.array(centers) - np.array(JAW_OFFSET), env.unwrapped.task.grippers[0], atol=1e-6)
    if env_id.endswith("TissueManipulation-v0"):
        distance = np.array(data["/" + series_entity(SERIES["goal_distance"][0], 0)]["Scalars:scalars"])[:, 0]
        assert len(distance) == summary["steps"] + 1 and distance[-1] < distance[0]
        assert summary["final_exposure"] == [None]


def test_a_recording_draws_the_hook_and_the_attachment_it_frees(tmp_path):
    """An episode with a hook swept along the stuck strip, energised: the recording holds
    the hook's tip (in the env's place) and the stuck and released vertices, which
    partition the episode's adhesion, the released growing."""
    import gymnasium as gym

    hook = {"start_low": [0.015, 0.0, 0.0], "start_high": [0.015, 0.0, 0.0], "workspace_low": [-0.05, -0.05, 0.0],
            "workspace_high": [0.2, 0.17, 0.15], "reach": 0.012, "release_energy": 5e3}
    env = gym.make("heml_gym/TissueRetraction-v1", scene={"hooks": {"hook": hook}, "adhesion": {"width": [0.02, 0.02]}},
                   settings={"max_steps": 50}, max_episode_steps=50)

    def sweep(obs):
        return np.array([0, 0, 0, -1, 0, 0.5, 0, 1], dtype=np.float32)

    sweep.reset = lambda: None
    path = tmp_path / "hook.rrd"
    record_rollouts(env, sweep, path=path, episodes=1, seed=SEED)
    data = _temporal(RrdReader(path).stream().collect())
    tips = data["/world/hook"]["Points3D:positions"]
    np.testing.assert_allclose(np.array(tips[-1]).reshape(-1, 3), env.unwrapped.task.hook_tips[0], atol=1e-6)
    stuck = [len(p) for p in data["/world/adhesion/stuck"]["Points3D:positions"]]
    released = [len(p) for p in data["/world/adhesion/released"]["Points3D:positions"]]
    total = int(env.unwrapped.task.stuck_at_start[0].sum())
    assert all(s + r == total for s, r in zip(stuck, released))
    assert released[0] == 0 and released[-1] > 0.8 * total and np.all(np.diff(released) >= 0)


def test_a_dissection_recording_draws_the_critical_structure_and_its_margin(tmp_path):
    """The common bile duct of GallbladderDissection, logged once: two capsules on its axis,
    the structure's radius and that radius plus the margin, each as long as the duct."""
    import gymnasium as gym

    env = gym.make("heml_gym/GallbladderDissection-v0", settings={"max_steps": 2}, max_episode_steps=2)
    path = tmp_path / "dissection.rrd"
    record_rollouts(env, scripted_policy(env.unwrapped.scene), path=path, episodes=1, seed=SEED)
    critical = env.unwrapped.scene.critical
    static = _static(RrdReader(path).stream().collect())["/world/critical"]
    (radii,) = static["Capsules3D:radii"]
    (lengths,) = static["Capsules3D:lengths"]
    np.testing.assert_allclose(radii, [critical.radius, critical.radius + critical.margin], rtol=1e-6)
    np.testing.assert_allclose(lengths, np.linalg.norm(np.subtract(critical.end, critical.start)), rtol=1e-6)


def test_a_push_recording_draws_the_paddles_blade_where_it_is(tmp_path):
    """PushRetraction's paddle is logged as its blade (its half extents, at its centre), and
    no jaws are drawn: the task has no grasper."""
    import gymnasium as gym

    env = gym.make("heml_gym/PushRetraction-v0", settings={"max_steps": 5}, max_episode_steps=5)
    path = tmp_path / "push.rrd"
    record_rollouts(env, scripted_policy(env.unwrapped.scene), path=path, episodes=1, seed=SEED)
    data = _temporal(RrdReader(path).stream().collect())
    paddle = env.unwrapped.task.instruments[0]
    np.testing.assert_allclose(np.array(data["/world/paddle"]["Boxes3D:centers"][-1]).reshape(-1, 3),
                               paddle.position, atol=1e-6)
    np.testing.assert_allclose(np.array(data["/world/paddle"]["Boxes3D:half_sizes"][-1]).reshape(-1, 3),
                               [paddle.spec.half_extents], rtol=1e-6)
    assert all(len(c or []) == 0 for c in data["/world/gripper"]["Boxes3D:centers"])


def test_a_recording_draws_a_shaft_that_touches_tissue_from_its_end_to_its_port(tmp_path):
    """A grasper on a port with ``shaft_radius``: its shaft is logged as a capsule of that
    radius from its end behind the jaws to the port, where the jaws are."""
    import gymnasium as gym

    port = [0.06, 0.04, 0.15]
    env = gym.make("heml_gym/TissueRetraction-v1", settings={"max_steps": 3}, max_episode_steps=3,
                   scene={"gripper": {"port": port, "shaft_radius": 0.004}})
    path = tmp_path / "shaft.rrd"
    record_rollouts(env, lambda obs: np.array([0.5, 0.0, -0.5, -1.0], dtype=np.float32), path=path, episodes=1,
                    seed=SEED)
    data = _temporal(RrdReader(path).stream().collect())["/world/shaft"]
    jaws = env.unwrapped.task.instruments[0].position[0]
    along = (jaws - port) / np.linalg.norm(jaws - port)
    end = jaws - 0.015 * along  # the shaft ends 15 mm behind the jaws
    np.testing.assert_allclose(np.array(data["Capsules3D:translations"][-1]).reshape(3), end, atol=1e-6)
    np.testing.assert_allclose(data["Capsules3D:lengths"][-1], np.linalg.norm(np.subtract(port, end)), rtol=1e-6)
    np.testing.assert_allclose(data["Capsules3D:radii"][-1], 0.004, rtol=1e-6)


def test_a_recording_turns_jaws_that_roll_along_their_axis(tmp_path):
    """Jaws on a port that roll are logged as a box long along their axis: the box's turn
    (its quaternion, read back) takes its y axis onto the jaws' axis where they are."""
    import gymnasium as gym

    scene = {"grasp": {"low": [0.08, 0.05, 0.008], "high": [0.12, 0.07, None], "surface": True},
             "gripper": {"port": [0.10, 0.06, 0.15], "jaw_length": 0.025, "roll_speed": 4.0}}
    env = gym.make("heml_gym/TissueRetraction-v1", settings={"max_steps": 3}, max_episode_steps=3, scene=scene)
    path = tmp_path / "roll.rrd"
    record_rollouts(env, lambda obs: np.array([0.0, 0.0, 0.0, -1.0, 1.0], dtype=np.float32), path=path, episodes=1,
                    seed=SEED)
    data = _temporal(RrdReader(path).stream().collect())["/world/gripper"]
    x, y, z, w = np.array(data["Boxes3D:quaternions"][-1]).reshape(4)
    turn = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])
    grasper = env.unwrapped.task.instruments[0]
    assert grasper.roll[0] == pytest.approx(1.2)  # 3 steps at 0.4 rad
    np.testing.assert_allclose(turn[:, 1], grasper.jaw_axes()[0], atol=1e-6)
    np.testing.assert_allclose(np.array(data["Boxes3D:half_sizes"][-1]).reshape(3)[1], 0.0125, rtol=1e-6)

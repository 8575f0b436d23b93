// The viewer's camera conventions (server/viewer/camera.js) against the rules' fixtures that the
// Rust and Python sides read too (tests/fixtures/rules/, written by scripts/make-rule-fixtures.py):
// a pose in any of the API's conventions is the camera the fixture's canonical world-to-camera
// describes; the camera the page sends back, and the nerfstudio path it exports, are that camera;
// a resized camera keeps pixel centres at integers; the point the page orbits is the one the
// depth range is measured from. Run by scripts/viewer-test.sh: node --test (Node >= 20.19).
import assert from 'node:assert/strict';
import { readFileSync } from 'node:fs';
import { test } from 'node:test';
import { cameraAt, nerfstudioPath, poseOf, sceneFrame } from '../../server/viewer/camera.js';

const rules = new URL('../../tests/fixtures/rules/', import.meta.url);
const fixture = (name) => JSON.parse(readFileSync(new URL(name, rules), 'utf8'));
const cameras = fixture('cameras.json');
const depthRange = fixture('depth_range.json');

function assertClose(got, want, tolerance, what) {
  const worst = Math.max(...got.flat().map((v, i) => Math.abs(v - want.flat()[i])));
  assert.ok(worst <= tolerance, `${what}: ${JSON.stringify(got)} vs ${JSON.stringify(want)}`);
}

/** The camera a canonical world-to-camera [R | t] describes: R's rows are its axes, -Rᵀt its centre. */
function canonical(w2c) {
  const row = (i) => w2c[i].slice(0, 3);
  const t = [0, 1, 2].map((i) => w2c[i][3]);
  const centre = [0, 1, 2].map((j) => -(row(0)[j] * t[0] + row(1)[j] * t[1] + row(2)[j] * t[2]));
  return { right: row(0), down: row(1), forward: row(2), centre };
}

const base = { width: 8, height: 6, intrinsics: { fx: 10, fy: 10, cx: 3.5, cy: 2.5 } };

test('every pose convention is the canonical camera', () => {
  for (const { matrix, kind, axes, w2c } of cameras.poses) {
    const pose = poseOf({ pose: { matrix, kind, axes } });
    const want = canonical(w2c);
    for (const axis of ['right', 'down', 'forward', 'centre']) {
      // The float32 pose is rigid to ~1e-7 only, and the page re-orthonormalises it.
      assertClose(pose[axis], want[axis], 1e-6, `${kind} ${axes} ${axis}`);
    }
  }
});

test('the camera the page sends and the path it exports are the camera it drew', () => {
  const poses = cameras.poses.filter((p) => p.kind === 'camera_to_world' && p.axes === 'opengl');
  for (const { matrix, w2c } of poses) {
    const sent = cameraAt(base, canonical(w2c), 1);
    assert.equal(sent.pose.kind, 'camera_to_world');
    assert.equal(sent.pose.axes, 'opencv');
    assertClose(canonical(w2c).centre, sent.pose.matrix.slice(0, 3).map((r) => r[3]), 1e-9, 'centre');
    assertClose(poseOf(sent).forward, canonical(w2c).forward, 1e-6, 'forward'); // float32: rigid to ~1e-7
    const exported = nerfstudioPath([sent], base, 24).camera_path[0].camera_to_world;
    assertClose(exported, matrix.flat(), 1e-6, 'nerfstudio camera_to_world (OpenGL)');
  }
});

test('a resized camera keeps pixel centres at integers', () => {
  for (const { camera: c, resized: want } of cameras.resized) {
    const from = { width: c.width, height: c.height, intrinsics: { fx: c.fx, fy: c.fy, cx: c.cx, cy: c.cy } };
    const got = cameraAt(from, canonical([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0]]), want.width / c.width);
    assert.deepEqual([got.width, got.height], [want.width, want.height]);
    const k = got.intrinsics;
    assertClose([k.fx, k.fy, k.cx, k.cy], [want.fx, want.fy, want.cx, want.cy], 1e-9, `${c.width}x${c.height}`);
  }
});

test('the page orbits the point the depth range is measured from', () => {
  const inFront = (rig) =>
    rig.convergence !== null &&
    rig.w2c.every((m) => {
      const { forward, centre } = canonical(m);
      return [0, 1, 2].reduce((s, i) => s + (rig.convergence.point[i] - centre[i]) * forward[i], 0) > 0;
    });
  const rigs = depthRange.rigs.filter(inFront);
  assert.ok(rigs.length >= 4, 'the fixture has rigs whose point is in front of every camera');
  for (const rig of rigs) {
    const [near, far] = rig.range;
    const frame = sceneFrame(rig.w2c.map(canonical), near, far);
    assertClose(frame.centre, rig.convergence.point, 1e-9, rig.name);
  }
});

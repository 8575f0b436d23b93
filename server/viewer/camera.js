// Camera maths. A pose is camera-to-world in OpenCV axes (x right, y down, z forward), the
// server's canonical form, kept as its three unit axes and its centre in world coordinates, so
// that a pose goes to the server exactly as the page drew it.

export const add = (a, b) => [a[0] + b[0], a[1] + b[1], a[2] + b[2]];
export const sub = (a, b) => [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
export const scale = (a, s) => [a[0] * s, a[1] * s, a[2] * s];
export const dot = (a, b) => a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
export const cross = (a, b) => [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];
export const length = (a) => Math.hypot(a[0], a[1], a[2]);
export const normalize = (a) => scale(a, 1 / (length(a) || 1));

/** Rodrigues: `v` rotated by `angle` about the unit `axis`. */
function rotate(v, axis, angle) {
  const c = Math.cos(angle);
  const s = Math.sin(angle);
  const k = cross(axis, v);
  const along = dot(axis, v) * (1 - c);
  return [0, 1, 2].map((i) => v[i] * c + k[i] * s + axis[i] * along);
}

/** Re-orthonormalises a pose (rounding drifts after many rotations), keeping its view axis. */
function orthonormal({ right, forward, centre }) {
  const f = normalize(forward);
  const r = normalize(sub(right, scale(f, dot(right, f))));
  return { right: r, down: cross(f, r), forward: f, centre };
}

/**
 * The pose of a camera in the API's JSON form (any `kind` and `axes`). World-to-camera
 * matrices are inverted as rigid transforms: the page only draws and orbits them.
 */
export function poseOf(camera) {
  const { matrix: m, kind, axes } = camera.pose;
  let column = (j) => [m[0][j], m[1][j], m[2][j]];
  let centre = column(3);
  if (kind === 'world_to_camera') {
    const row = (i) => [m[i][0], m[i][1], m[i][2]];
    const t = column(3);
    column = row; // the rows of R are the camera's axes in world coordinates
    centre = scale(add(add(scale(row(0), t[0]), scale(row(1), t[1])), scale(row(2), t[2])), -1);
  }
  // OpenGL cameras look down -z with y up: flipping y and z gives OpenCV's axes.
  const flip = axes === 'opengl' ? -1 : 1;
  return orthonormal({ right: column(0), forward: scale(column(2), flip), centre });
}

/** `{fx, fy, cx, cy}` of a camera given by `intrinsics` (object or 3x3) or `K`. */
export function intrinsicsOf(camera) {
  const k = camera.intrinsics ?? camera.K;
  if (Array.isArray(k)) return { fx: k[0][0], fy: k[1][1], cx: k[0][2], cy: k[1][2] };
  return { fx: k.fx, fy: k.fy, cx: k.cx, cy: k.cy };
}

/**
 * The API camera for `pose` seen through `base`'s lens, at `fraction` of `base`'s size.
 * Pixel centres sit at integer coordinates, so the principal point scales about -0.5.
 */
export function cameraAt(base, pose, fraction) {
  const width = Math.max(1, Math.round(base.width * fraction));
  const height = Math.max(1, Math.round(base.height * fraction));
  const sx = width / base.width;
  const sy = height / base.height;
  const k = intrinsicsOf(base);
  const { right: r, down: d, forward: f, centre: c } = pose;
  return {
    width,
    height,
    intrinsics: { fx: k.fx * sx, fy: k.fy * sy, cx: (k.cx + 0.5) * sx - 0.5, cy: (k.cy + 0.5) * sy - 0.5 },
    pose: {
      matrix: [[r[0], d[0], f[0], c[0]], [r[1], d[1], f[1], c[1]], [r[2], d[2], f[2], c[2]], [0, 0, 0, 1]],
      kind: 'camera_to_world',
      axes: 'opencv',
    },
  };
}

/** Solves the 3x3 system `a x = b` (Cramer); null when `a` is near singular. */
function solve3(a, b) {
  const det = (m) => dot(m[0], cross(m[1], m[2]));
  const d = det(a);
  const size = Math.max(...a.flat().map(Math.abs));
  if (!(Math.abs(d) > 1e-6 * size ** 3)) return null;
  const withColumn = (j) => a.map((row, i) => row.map((v, k) => (k === j ? b[i] : v)));
  return [0, 1, 2].map((j) => det(withColumn(j)) / d);
}

/**
 * Where the capture looks and which way is up. The centre is the point nearest to every
 * camera's optical axis (cameras around an object); when the axes are near parallel (a
 * forward-facing capture) it is the cameras' mid-depth point instead. Up is against the mean of
 * the cameras' down axes.
 */
export function sceneFrame(poses, near, far) {
  const a = [[0, 0, 0], [0, 0, 0], [0, 0, 0]];
  const b = [0, 0, 0];
  for (const { forward: f, centre: c } of poses) {
    for (let i = 0; i < 3; i++) {
      for (let j = 0; j < 3; j++) {
        const p = (i === j ? 1 : 0) - f[i] * f[j];
        a[i][j] += p;
        b[i] += p * c[j];
      }
    }
  }
  const middle = (near + far) / 2;
  const ahead = (p) => poses.every(({ forward, centre }) => dot(sub(p, centre), forward) > 0);
  let centre = solve3(a, b);
  if (!centre || !ahead(centre)) {
    centre = scale(poses.reduce((s, { forward, centre: c }) => add(s, add(c, scale(forward, middle))), [0, 0, 0]), 1 / poses.length);
  }
  const up = normalize(scale(poses.reduce((s, p) => add(s, p.down), [0, 0, 0]), -1));
  const radius = Math.max(near, ...poses.map((p) => length(sub(p.centre, centre))));
  return { centre, up, radius };
}

// A view: the virtual camera's pose and the point it orbits (the pivot).

/** The view from `pose`, orbiting the point of its optical axis nearest to the scene's centre. */
export function viewFrom(pose, frame) {
  const depth = Math.max(dot(sub(frame.centre, pose.centre), pose.forward), frame.radius * 0.05);
  return { pose, pivot: add(pose.centre, scale(pose.forward, depth)) };
}

/** Turns the whole view (camera and pivot) by `angle` about `axis` through `point`. */
function turn(view, axis, angle, point) {
  const r = (v) => rotate(v, axis, angle);
  const about = (p) => add(point, r(sub(p, point)));
  const { right, forward, centre } = view.pose;
  return { pose: orthonormal({ right: r(right), forward: r(forward), centre: about(centre) }), pivot: about(view.pivot) };
}

/**
 * Orbits about the pivot: `yaw` about the scene's up axis, then `pitch` about the camera's
 * right axis (radians; positive yaw moves the camera to its right, positive pitch down).
 */
export function orbit(view, up, yaw, pitch) {
  const turned = turn(view, up, yaw, view.pivot);
  return turn(turned, turned.pose.right, pitch, turned.pivot);
}

/** Rolls about the view axis (radians, clockwise as seen by the camera). */
export function roll(view, angle) {
  return turn(view, view.pose.forward, angle, view.pose.centre);
}

/** Moves camera and pivot across the view by (dx, dy) pivot distances (right, down). */
export function pan(view, dx, dy) {
  const { right, down, centre } = view.pose;
  const d = length(sub(view.pivot, centre));
  const shift = add(scale(right, dx * d), scale(down, dy * d));
  return { pose: { ...view.pose, centre: add(centre, shift) }, pivot: add(view.pivot, shift) };
}

/** Moves the camera towards the pivot (factor < 1) or away (> 1); it never reaches it. */
export function dolly(view, factor, minDistance) {
  const offset = sub(view.pose.centre, view.pivot);
  const distance = Math.max(length(offset) * factor, minDistance);
  return { ...view, pose: { ...view.pose, centre: add(view.pivot, scale(normalize(offset), distance)) } };
}

/**
 * Cameras (API form, camera-to-world OpenCV as `cameraAt` makes them, all of `base`'s lens) as
 * nerfstudio's camera_path.json, what its viewer exports and `ns-render camera-path` and
 * `scnerf render --path` read: per frame `camera_to_world` (16 numbers, row-major, OpenGL axes),
 * the vertical `fov` in degrees and `aspect`; the render size, `fps` and `seconds`. nerfstudio's
 * principal point is the image centre.
 */
export function nerfstudioPath(cameras, base, fps) {
  const { fy } = intrinsicsOf(base);
  const fov = (2 * Math.atan(base.height / 2 / fy) * 180) / Math.PI;
  const aspect = base.width / base.height;
  const path = cameras.map((camera) => {
    const m = camera.pose.matrix;
    // OpenCV (x right, y down, z forward) to OpenGL (x right, y up, z back): flip y and z
    const gl = m.map((row, i) => (i < 3 ? [row[0], -row[1], -row[2], row[3]] : row));
    return { camera_to_world: gl.flat(), fov, aspect };
  });
  return {
    camera_type: 'perspective',
    render_width: base.width,
    render_height: base.height,
    camera_path: path,
    fps,
    seconds: cameras.length / fps,
  };
}

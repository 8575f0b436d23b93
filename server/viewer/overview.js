// The 3-D overview: the capture's cameras and the virtual camera as frusta, drawn on a 2-D
// canvas through a fixed perspective camera that looks at the scene from above and behind the
// capture. Clicking a captured camera snaps the view to it.

import { add, cross, dot, intrinsicsOf, length, normalize, poseOf, scale, sub } from './camera.js';

const COLOURS = { camera: '#9aa4b8', used: '#f59e0b', virtual: '#38bdf8', pivot: '#f472b6' };
/** Frustum depth, as a fraction of the scene's radius. */
const FRUSTUM = 0.3;
/** Clicks this close (CSS pixels) to a camera's centre pick it. */
const PICK_RADIUS = 14;

/** The overview's own camera: above and behind the capture, looking at its centre. */
function overviewPose(frame, poses) {
  const meanForward = scale(poses.reduce((s, p) => add(s, p.forward), [0, 0, 0]), 1 / poses.length);
  // Cameras facing one way: look over their shoulders. Cameras all around: over the first one's.
  const back = scale(length(meanForward) > 0.5 ? meanForward : poses[0].forward, -1);
  let level = sub(back, scale(frame.up, dot(back, frame.up)));
  if (length(level) < 1e-3) level = cross(frame.up, Math.abs(frame.up[0]) < 0.9 ? [1, 0, 0] : [0, 1, 0]);
  const direction = normalize(add(scale(normalize(level), 2), scale(frame.up, 1.2)));
  const centre = add(frame.centre, scale(direction, 3 * frame.radius));
  const forward = normalize(sub(frame.centre, centre));
  const right = normalize(cross(scale(frame.up, -1), forward));
  return { right, down: cross(forward, right), forward, centre };
}

/** Apex and the four far corners of a camera's frustum, `depth` ahead of it. */
function frustum(pose, camera, depth) {
  const k = intrinsicsOf(camera);
  const corner = (u, v) =>
    add(pose.centre, scale(add(add(scale(pose.right, (u - k.cx) / k.fx), scale(pose.down, (v - k.cy) / k.fy)), pose.forward), depth));
  const [w, h] = [camera.width - 0.5, camera.height - 0.5];
  return [pose.centre, corner(-0.5, -0.5), corner(w, -0.5), corner(w, h), corner(-0.5, h)];
}

export class Overview {
  constructor(canvas, onPick) {
    this.canvas = canvas;
    this.scene = null;
    canvas.addEventListener('click', (e) => {
      const picked = this.pick(e);
      if (picked !== null) onPick(picked);
    });
  }

  /** `frame`: the scene's {centre, up, radius} (camera.js sceneFrame). */
  setScene(scene, frame) {
    const poses = scene.cameras.map(poseOf);
    this.scene = { cameras: scene.cameras, poses, frame, eye: overviewPose(frame, poses) };
    const depth = FRUSTUM * frame.radius;
    // Framed once per scene, on the captured frusta: moving the camera does not rescale it.
    const points = poses.flatMap((p, i) => frustum(p, scene.cameras[i], depth)).concat([frame.centre]);
    const projected = points.map((p) => this.project(p)).filter(Boolean);
    const xs = projected.map(([x]) => x);
    const ys = projected.map(([, y]) => y);
    this.bounds = { x0: Math.min(...xs), x1: Math.max(...xs), y0: Math.min(...ys), y1: Math.max(...ys) };
  }

  /** Normalised image coordinates (x right, y down) through the overview camera, or null behind it. */
  project(p) {
    const { eye } = this.scene;
    const q = sub(p, eye.centre);
    const z = dot(q, eye.forward);
    return z > 1e-9 ? [dot(q, eye.right) / z, dot(q, eye.down) / z] : null;
  }

  /** Canvas pixels of a world point, or null. */
  toCanvas(p) {
    const xy = this.project(p);
    if (!xy) return null;
    const { width, height } = this.canvas;
    const { x0, x1, y0, y1 } = this.bounds;
    const s = 0.85 * Math.min(width / Math.max(x1 - x0, 1e-9), height / Math.max(y1 - y0, 1e-9));
    return [width / 2 + (xy[0] - (x0 + x1) / 2) * s, height / 2 + (xy[1] - (y0 + y1) / 2) * s];
  }

  /** Index of the captured camera under a click, or null. */
  pick(e) {
    if (!this.scene) return null;
    const rect = this.canvas.getBoundingClientRect();
    const ratio = this.canvas.width / rect.width;
    const click = [(e.clientX - rect.left) * ratio, (e.clientY - rect.top) * ratio];
    let best = null;
    this.scene.poses.forEach((pose, i) => {
      const at = this.toCanvas(pose.centre);
      const distance = at && Math.hypot(at[0] - click[0], at[1] - click[1]);
      if (at && distance < PICK_RADIUS * ratio && (best === null || distance < best.distance)) best = { i, distance };
    });
    return best?.i ?? null;
  }

  /** Keeps the canvas's pixels matched to its displayed size, so lines stay sharp. */
  fitCanvas() {
    const ratio = window.devicePixelRatio || 1;
    const width = Math.round(this.canvas.clientWidth * ratio);
    const height = Math.round(this.canvas.clientHeight * ratio);
    if (width > 0 && (this.canvas.width !== width || this.canvas.height !== height)) {
      this.canvas.width = width;
      this.canvas.height = height;
    }
    return ratio;
  }

  /** Draws every captured camera (`used`: indices of the last render's sources), the virtual one and its pivot. */
  draw(view, base, used) {
    if (!this.scene) return;
    const ratio = this.fitCanvas();
    const ctx = this.canvas.getContext('2d');
    ctx.clearRect(0, 0, this.canvas.width, this.canvas.height);
    const depth = FRUSTUM * this.scene.frame.radius;
    this.scene.poses.forEach((pose, i) => {
      const colour = used.includes(i) ? COLOURS.used : COLOURS.camera;
      this.drawFrustum(ctx, frustum(pose, this.scene.cameras[i], depth), colour, ratio * (used.includes(i) ? 2 : 1));
      const apex = this.toCanvas(pose.centre);
      if (apex) {
        ctx.fillStyle = colour;
        ctx.font = `${12 * ratio}px system-ui, sans-serif`;
        ctx.fillText(String(i + 1), apex[0] + 4 * ratio, apex[1] - 4 * ratio);
      }
    });
    this.drawFrustum(ctx, frustum(view.pose, base, depth), COLOURS.virtual, 2 * ratio);
    const pivot = this.toCanvas(view.pivot);
    if (pivot) {
      ctx.fillStyle = COLOURS.pivot;
      ctx.beginPath();
      ctx.arc(pivot[0], pivot[1], 3 * ratio, 0, 2 * Math.PI);
      ctx.fill();
    }
  }

  /** Lines from the apex to the corners, the far rectangle, and a tick on its top edge (the camera's up). */
  drawFrustum(ctx, points, colour, lineWidth) {
    const [apex, ...corners] = points.map((p) => this.toCanvas(p));
    if (!apex || corners.some((c) => !c)) return;
    ctx.strokeStyle = colour;
    ctx.lineWidth = lineWidth;
    ctx.beginPath();
    for (const c of corners) {
      ctx.moveTo(...apex);
      ctx.lineTo(...c);
    }
    ctx.moveTo(...corners[3]);
    for (const c of corners) ctx.lineTo(...c);
    const mean = (ps) => [0, 1].map((k) => ps.reduce((s, p) => s + p[k], 0) / ps.length);
    const top = mean(corners.slice(0, 2));
    const middle = mean(corners);
    ctx.moveTo(...top);
    ctx.lineTo(top[0] + (top[0] - middle[0]) * 0.5, top[1] + (top[1] - middle[1]) * 0.5);
    ctx.stroke();
  }
}

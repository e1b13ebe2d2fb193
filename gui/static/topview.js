// The XY plane from above (x right, y up, metres): the reachable annulus, the obstacle and
// its inflated hull, the waypoints, the planned and travelled paths, the arm. The mouse edits
// the draft task: waypoints added (click), moved (drag), deleted (right click); the obstacle
// placed (click), moved (drag), resized (wheel) and turned (shift + wheel).
"use strict";

const GRAB_PIXELS = 9; // how near a waypoint a press takes it

class TopView {
  constructor(canvas, geometry, draft, onEdit) {
    this.canvas = canvas;
    // opaque: the background is filled, and the compositor copies an opaque canvas unblended
    this.context = canvas.getContext("2d", { alpha: false });
    this.geometry = geometry;
    this.draft = draft; // {waypoints: [...], obstacle: {...} | null}, shared with the inputs
    this.onEdit = onEdit;
    this.mode = "waypoints";
    this.editable = true; // false on a read-only page: the mouse edits nothing
    this.joints = null;
    this.path = [];
    this.plan = [];
    this.span = geometry.r_max * 1.1; // metres from the centre to the edge
    const ratio = window.devicePixelRatio || 1;
    // its size in CSS pixels, read once: read while drawing, after the numbers were written,
    // it forced the browser to lay the page out again every frame
    this.size = canvas.clientWidth;
    canvas.width = this.size * ratio;
    canvas.height = this.size * ratio;
    this.context.scale(ratio, ratio);
    this.dragging = null;
    canvas.addEventListener("mousedown", (e) => this.press(e));
    canvas.addEventListener("mousemove", (e) => this.move(e));
    window.addEventListener("mouseup", () => { this.dragging = null; });
    canvas.addEventListener("contextmenu", (e) => this.remove(e));
    canvas.addEventListener("wheel", (e) => this.wheel(e), { passive: false });
  }

  // --- coordinates: CSS pixels of the canvas <-> metres ---
  toScreen(x, y) {
    const size = this.size / 2;
    return [size + (x / this.span) * size, size - (y / this.span) * size];
  }

  toWorld(event) {
    const box = this.canvas.getBoundingClientRect();
    const size = box.width / 2;
    const px = event.clientX - box.left, py = event.clientY - box.top;
    return [round((px - size) / size * this.span), round((size - py) / size * this.span)];
  }

  // --- mouse ---
  nearestWaypoint(event) {
    const box = this.canvas.getBoundingClientRect();
    const px = event.clientX - box.left, py = event.clientY - box.top;
    let found = -1, best = GRAB_PIXELS;
    this.draft.waypoints.forEach((w, i) => {
      const [sx, sy] = this.toScreen(w.x, w.y);
      const d = Math.hypot(sx - px, sy - py);
      if (d < best) { best = d; found = i; }
    });
    return found;
  }

  press(event) {
    if (event.button !== 0 || !this.editable) return;
    const [x, y] = this.toWorld(event);
    if (this.mode === "waypoints") {
      const index = this.nearestWaypoint(event);
      if (index >= 0) {
        this.dragging = { waypoint: index };
        return;
      }
      const last = this.draft.waypoints[this.draft.waypoints.length - 1];
      this.draft.waypoints.push({ t: last ? round(last.t + 1.5) : 0, x, y, z: last ? last.z : 0.22 });
      this.dragging = { waypoint: this.draft.waypoints.length - 1 };
    } else {
      const o = this.draft.obstacle;
      if (o && this.insideObstacle(o, x, y)) {
        this.dragging = { obstacle: [x - o.x, y - o.y] };
        return;
      }
      this.draft.obstacle = Object.assign(defaultObstacle(), o || {}, { x, y });
      this.dragging = { obstacle: [0, 0] };
    }
    this.onEdit();
  }

  move(event) {
    if (!this.dragging) return;
    const [x, y] = this.toWorld(event);
    if (this.dragging.waypoint !== undefined) {
      Object.assign(this.draft.waypoints[this.dragging.waypoint], { x, y });
    } else {
      const [dx, dy] = this.dragging.obstacle;
      Object.assign(this.draft.obstacle, { x: round(x - dx), y: round(y - dy) });
    }
    this.onEdit();
  }

  remove(event) {
    event.preventDefault();
    if (this.mode !== "waypoints" || !this.editable) return;
    const index = this.nearestWaypoint(event);
    if (index >= 0) {
      this.draft.waypoints.splice(index, 1);
      this.onEdit();
    }
  }

  wheel(event) {
    const o = this.draft.obstacle;
    if (this.mode !== "obstacle" || !o || !this.editable) return;
    event.preventDefault();
    const direction = event.deltaY < 0 ? 1 : -1;
    if (event.shiftKey) {
      o.yaw_deg = (o.yaw_deg + 5 * direction + 540) % 360 - 180;
    } else {
      const factor = direction > 0 ? 1.1 : 1 / 1.1;
      o.long_diameter = round(o.long_diameter * factor);
      o.short_diameter = round(o.short_diameter * factor);
    }
    this.onEdit();
  }

  insideObstacle(o, x, y) {
    const yaw = o.yaw_deg * Math.PI / 180, dx = x - o.x, dy = y - o.y;
    const u = dx * Math.cos(yaw) + dy * Math.sin(yaw), v = -dx * Math.sin(yaw) + dy * Math.cos(yaw);
    return (u / (o.long_diameter / 2)) ** 2 + (v / (o.short_diameter / 2)) ** 2 <= 1;
  }

  // --- drawing ---
  draw() {
    const c = this.context, g = this.geometry;
    const size = this.size, scale = size / 2 / this.span;
    c.fillStyle = "#ffffff";
    c.fillRect(0, 0, size, size);
    const [cx, cy] = this.toScreen(0, 0);
    c.fillStyle = "#e8f5e9";
    c.beginPath();
    c.arc(cx, cy, g.r_max * scale, 0, 2 * Math.PI);
    c.arc(cx, cy, g.r_min * scale, 0, 2 * Math.PI, true);
    c.fill();
    const o = this.draft.obstacle;
    if (o) {
      const grow = o.tool_radius + o.margin;
      this.ellipse(o, o.long_diameter / 2 + grow, o.short_diameter / 2 + grow, scale, null, "#c62828");
      this.ellipse(o, o.long_diameter / 2, o.short_diameter / 2, scale, "#8d6e63", null);
    }
    this.polyline(this.plan, "#1e88e5", [5, 4]);
    this.polyline(this.path, "#e65100", []);
    c.font = "11px system-ui";
    this.draft.waypoints.forEach((w, i) => {
      const [x, y] = this.toScreen(w.x, w.y);
      c.fillStyle = "#1565c0";
      c.beginPath();
      c.arc(x, y, 5, 0, 2 * Math.PI);
      c.fill();
      c.fillText(String(i + 1), x + 7, y - 7);
    });
    if (this.joints) this.drawArm(this.joints);
  }

  ellipse(o, a, b, scale, fill, stroke) {
    const c = this.context, [x, y] = this.toScreen(o.x, o.y);
    c.beginPath();
    c.ellipse(x, y, a * scale, b * scale, -o.yaw_deg * Math.PI / 180, 0, 2 * Math.PI);
    if (fill) { c.fillStyle = fill; c.fill(); }
    if (stroke) { c.strokeStyle = stroke; c.setLineDash([3, 3]); c.stroke(); c.setLineDash([]); }
  }

  polyline(points, color, dash) {
    if (points.length < 2) return;
    const c = this.context;
    c.strokeStyle = color;
    c.lineWidth = 1.5;
    c.setLineDash(dash);
    c.beginPath();
    points.forEach(([x, y], i) => {
      const [sx, sy] = this.toScreen(x, y);
      if (i === 0) c.moveTo(sx, sy); else c.lineTo(sx, sy);
    });
    c.stroke();
    c.setLineDash([]);
  }

  drawArm([theta1, theta2]) {
    const g = this.geometry, c = this.context;
    const elbow = [g.a1 * Math.cos(theta1), g.a1 * Math.sin(theta1)];
    const tool = [elbow[0] + g.a2 * Math.cos(theta1 + theta2), elbow[1] + g.a2 * Math.sin(theta1 + theta2)];
    c.strokeStyle = "rgba(251, 140, 0, 0.8)";
    c.lineWidth = 6;
    c.lineCap = "round";
    c.beginPath();
    c.moveTo(...this.toScreen(0, 0));
    c.lineTo(...this.toScreen(...elbow));
    c.lineTo(...this.toScreen(...tool));
    c.stroke();
    c.lineWidth = 1;
  }
}

function defaultObstacle() {
  return { x: 0.4, y: 0, long_diameter: 0.1, short_diameter: 0.06, height: 0.3, yaw_deg: 0, tool_radius: 0.01, margin: 0.01 };
}

function round(value) {
  return Math.round(value * 1000) / 1000; // millimetres: what a typed input shows
}

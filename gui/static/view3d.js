// The arm in 3D (three.js, z up, metres): base column, both links, the quill at d3, the
// obstacle (solid) and its inflated hull (wire), the planned path and the path travelled.
"use strict";

const PATH_CAPACITY = 20000; // points of the path travelled, as the server keeps (gui/state.py)
const SOFTWARE_WEBGL = /SwiftShader|llvmpipe|softpipe|software/i;

// How this browser draws the 3D view: "webgl" where its WebGL has a GPU; "canvas" (Canvas 2D,
// canvas3d.js) where WebGL would be rasterised in software, or where the page's address asks
// for it (?view3d=canvas or ?view3d=webgl).
function chooseRenderer() {
  const asked = new URLSearchParams(location.search).get("view3d");
  if (asked === "webgl" || asked === "canvas") return asked;
  const gl = document.createElement("canvas").getContext("webgl");
  if (!gl) return "canvas";
  const info = gl.getExtension("WEBGL_debug_renderer_info");
  const name = info ? gl.getParameter(info.UNMASKED_RENDERER_WEBGL) : "";
  const lose = gl.getExtension("WEBGL_lose_context");
  if (lose) lose.loseContext(); // a context held for nothing counts against the browser's few
  return SOFTWARE_WEBGL.test(name) ? "canvas" : "webgl";
}

class Arm3D {
  // requestFrame: asks the page for a frame, when the view changed by itself (turned by the
  // mouse, resized)
  constructor(container, geometry, requestFrame) {
    this.geometry = geometry;
    this.requestFrame = requestFrame;
    this.kind = chooseRenderer();
    this.renderer = this.kind === "webgl"
      ? new THREE.WebGLRenderer({ antialias: true })
      : new CanvasSceneRenderer();
    this.renderer.setPixelRatio(window.devicePixelRatio);
    this.renderer.setClearColor(0xf7f9fa);
    container.appendChild(this.renderer.domElement);
    this.scene = new THREE.Scene();
    this.camera = new THREE.PerspectiveCamera(40, 1, 0.01, 20);
    this.camera.up.set(0, 0, 1);
    this.camera.position.set(1.1, -1.2, 1.0);
    this.controls = new THREE.OrbitControls(this.camera, this.renderer.domElement);
    this.controls.target.set(0.2, 0, 0.2);
    this.controls.update();
    this.controls.addEventListener("change", () => { this.dirty = true; this.requestFrame(); });
    this.scene.add(new THREE.HemisphereLight(0xffffff, 0x8899aa, 0.9));
    const sun = new THREE.DirectionalLight(0xffffff, 0.6);
    sun.position.set(1, -1, 2);
    this.scene.add(sun);
    const grid = new THREE.GridHelper(1.4, 14, 0xb0bec5, 0xdde3e6);
    grid.rotation.x = Math.PI / 2;
    grid.renderOrder = -1; // the floor, under everything
    this.scene.add(grid);
    this.buildArm();
    this.plan = this.line(0x1e88e5, 2);
    this.travelled = this.line(0xe65100, PATH_CAPACITY);
    this.obstacle = new THREE.Group();
    this.scene.add(this.obstacle);
    this.waypoints = new THREE.Group();
    this.scene.add(this.waypoints);
    this.resize(container);
    new ResizeObserver(() => this.resize(container)).observe(container);
  }

  buildArm() {
    const g = this.geometry;
    const metal = (color) => new THREE.MeshLambertMaterial({ color });
    const column = new THREE.Mesh(new THREE.CylinderGeometry(0.045, 0.06, g.d0, 16), metal(0x607d8b));
    column.rotation.x = Math.PI / 2;
    column.position.z = g.d0 / 2;
    this.scene.add(column);
    this.shoulder = new THREE.Group(); // turns by theta1 about the column
    this.shoulder.position.z = g.d0;
    this.scene.add(this.shoulder);
    const link1 = new THREE.Mesh(new THREE.BoxGeometry(g.a1, 0.07, 0.04), metal(0xffb300));
    link1.position.set(g.a1 / 2, 0, 0.04);
    this.shoulder.add(link1);
    this.elbow = new THREE.Group(); // turns by theta2 at the end of link 1
    this.elbow.position.x = g.a1;
    this.shoulder.add(this.elbow);
    const link2 = new THREE.Mesh(new THREE.BoxGeometry(g.a2, 0.06, 0.035), metal(0xfb8c00));
    link2.position.set(g.a2 / 2, 0, 0);
    this.elbow.add(link2);
    this.quillLength = g.d3_max + 0.12;
    this.quill = new THREE.Mesh(new THREE.CylinderGeometry(0.012, 0.012, this.quillLength, 8), metal(0x90a4ae));
    this.quill.rotation.x = Math.PI / 2;
    this.elbow.add(this.quill);
    this.tip = new THREE.Mesh(new THREE.SphereGeometry(0.014, 8, 6), metal(0xd32f2f));
    this.elbow.add(this.tip);
    this.setJoints([0, 0, 0]);
  }

  line(color, capacity) {
    const geometry = new THREE.BufferGeometry();
    geometry.setAttribute("position", new THREE.BufferAttribute(new Float32Array(capacity * 3), 3));
    geometry.setDrawRange(0, 0);
    geometry.getAttribute("position").setUsage(THREE.DynamicDrawUsage);
    const line = new THREE.Line(geometry, new THREE.LineBasicMaterial({ color }));
    line.frustumCulled = false;
    this.scene.add(line);
    return line;
  }

  setLine(line, points) {
    let attribute = line.geometry.getAttribute("position");
    if (attribute.count < points.length) {
      attribute = new THREE.BufferAttribute(new Float32Array(points.length * 3), 3);
      line.geometry.setAttribute("position", attribute);
    }
    points.forEach((point, i) => attribute.setXYZ(i, ...point));
    attribute.needsUpdate = true;
    line.geometry.setDrawRange(0, points.length);
    line.userData.written = points.length;
    this.dirty = true;
  }

  // The path travelled grows at its end: only its new points are written and sent to WebGL
  // (not the whole buffer of PATH_CAPACITY points, every frame).
  extendLine(line, points, restart) {
    const written = restart || points.length < (line.userData.written || 0) ? 0 : line.userData.written || 0;
    if (written === points.length) {
      if (restart) this.setLine(line, points);
      return;
    }
    if (points.length > line.geometry.getAttribute("position").count) return this.setLine(line, points);
    const attribute = line.geometry.getAttribute("position");
    for (let i = written; i < points.length; i++) attribute.setXYZ(i, ...points[i]);
    attribute.updateRange.offset = written * 3;
    attribute.updateRange.count = (points.length - written) * 3;
    attribute.needsUpdate = true;
    line.geometry.setDrawRange(0, points.length);
    line.userData.written = points.length;
    this.dirty = true;
  }

  setJoints([theta1, theta2, d3]) {
    const g = this.geometry;
    this.shoulder.rotation.z = theta1;
    this.elbow.rotation.z = theta2;
    const tipZ = -d3; // the tool at z = d0 - d3, the shoulder at d0
    this.quill.position.set(g.a2, 0, tipZ + this.quillLength / 2);
    this.tip.position.set(g.a2, 0, tipZ);
    this.dirty = true;
  }

  setTask(task) {
    for (const group of [this.obstacle, this.waypoints]) {
      while (group.children.length) group.remove(group.children[0]); // r111 has no clear()
    }
    for (const w of (task && task.waypoints) || []) {
      const dot = new THREE.Mesh(new THREE.SphereGeometry(0.008, 8, 6), new THREE.MeshBasicMaterial({ color: 0x1565c0 }));
      dot.position.set(w.x, w.y, w.z);
      this.waypoints.add(dot);
    }
    const o = task && task.obstacle;
    if (o) {
      const grow = o.tool_radius + o.margin;
      const cylinder = (a, b, object) => { // a unit cylinder stretched to the ellipse
        object.rotation.x = Math.PI / 2;
        object.scale.set(a, o.height, b);
        object.position.z = o.height / 2;
        return object;
      };
      const unit = new THREE.CylinderGeometry(1, 1, 1, 32);
      this.obstacle.add(cylinder(o.long_diameter / 2, o.short_diameter / 2,
        new THREE.Mesh(unit, new THREE.MeshLambertMaterial({ color: 0x8d6e63 }))));
      this.obstacle.add(cylinder(o.long_diameter / 2 + grow, o.short_diameter / 2 + grow,
        new THREE.LineSegments(new THREE.EdgesGeometry(unit),
          new THREE.LineBasicMaterial({ color: 0xc62828, transparent: true, opacity: 0.5 }))));
      this.obstacle.position.set(o.x, o.y, 0);
      this.obstacle.rotation.z = o.yaw_deg * Math.PI / 180;
    }
    this.dirty = true;
  }

  resize(container) {
    const width = container.clientWidth, height = container.clientHeight;
    this.renderer.setSize(width, height);
    this.camera.aspect = width / Math.max(1, height);
    this.camera.updateProjectionMatrix();
    this.dirty = true;
    this.requestFrame();
  }

  render() {
    if (!this.dirty) return false;
    this.renderer.render(this.scene, this.camera);
    this.dirty = false;
    return true;
  }
}

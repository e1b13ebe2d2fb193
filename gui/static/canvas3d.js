// A three.js scene drawn with Canvas 2D: faces flat-shaded and sorted back to front (the
// painter's algorithm), lines in short runs sorted with them. For browsers whose WebGL runs in
// software (no GPU: SwiftShader, llvmpipe): there every WebGL frame is rasterised on the CPU and
// read back for the compositor while the page waits, which cost two pages more than half a core
// and held each frame up. Drawing a few hundred flat faces with Canvas 2D costs a fraction of it.
//
// It draws what view3d.js builds and nothing more: meshes of THREE.Geometry (their front faces,
// Lambert or Basic materials), THREE.Line and THREE.LineSegments of BufferGeometry (their draw
// range, one colour or per-vertex colours, opaque or transparent), a hemisphere light and
// directional lights. Faces crossing the camera's near plane are left out, not clipped.
"use strict";

const LINE_RUN = 8; // points of a line drawn as one sorted element

class CanvasSceneRenderer {
  constructor() {
    this.domElement = document.createElement("canvas");
    // opaque: the background is filled, and the compositor copies an opaque canvas unblended
    this.context = this.domElement.getContext("2d", { alpha: false });
    this.pixelRatio = 1;
    this.width = 1;
    this.height = 1;
    this.clearColor = "#ffffff";
    this.elements = []; // this frame's faces and runs of lines: their points on the canvas, style, depth
    this.viewProjection = new THREE.Matrix4();
    this.cameraPosition = new THREE.Vector3();
    this.world = []; // scratch: a mesh's vertices in world coordinates
    this.screen = []; // ... and on the canvas (x, y in CSS pixels, w: the depth)
  }

  setPixelRatio(ratio) {
    this.pixelRatio = ratio;
    this.setSize(this.width, this.height);
  }

  setClearColor(color) {
    this.clearColor = `#${new THREE.Color(color).getHexString()}`;
  }

  setSize(width, height) {
    this.width = width;
    this.height = height;
    this.domElement.width = Math.max(1, Math.round(width * this.pixelRatio));
    this.domElement.height = Math.max(1, Math.round(height * this.pixelRatio));
    this.domElement.style.width = `${width}px`;
    this.domElement.style.height = `${height}px`;
  }

  render(scene, camera) {
    scene.updateMatrixWorld();
    camera.updateMatrixWorld();
    this.viewProjection.multiplyMatrices(camera.projectionMatrix, camera.matrixWorldInverse);
    this.cameraPosition.setFromMatrixPosition(camera.matrixWorld);
    this.lights = { sky: new THREE.Color(0, 0, 0), ground: new THREE.Color(0, 0, 0), suns: [] };
    scene.traverseVisible((object) => this.addLight(object));
    const context = this.context;
    context.setTransform(this.pixelRatio, 0, 0, this.pixelRatio, 0, 0);
    context.fillStyle = this.clearColor;
    context.fillRect(0, 0, this.width, this.height);
    this.elements.length = 0;
    scene.traverseVisible((object) => {
      if (object.isMesh) this.addMesh(object);
      else if (object.isLine) this.addLine(object);
    });
    // as three.js: renderOrder first (the grid on the floor under everything), then far to near
    this.elements.sort((a, b) => a.order - b.order || b.depth - a.depth);
    this.draw(context);
  }

  // Consecutive elements of one style are drawn as one path: the cost is per path, and most
  // of the scene comes in runs of a style (both triangles of a box's side, a line's runs).
  draw(context) {
    context.lineJoin = "round";
    let batch = null;
    const flush = () => {
      if (batch === null) return;
      if (batch.fill) {
        context.fillStyle = batch.style;
        context.fill();
      } else {
        context.strokeStyle = batch.style;
        context.lineWidth = batch.width;
        context.stroke();
      }
    };
    for (const element of this.elements) {
      if (batch === null || element.fill !== batch.fill || element.style !== batch.style
        || element.width !== batch.width) {
        flush();
        batch = element;
        context.beginPath();
      }
      const points = element.points;
      context.moveTo(points[0], points[1]);
      for (let i = 2; i < points.length; i += 2) context.lineTo(points[i], points[i + 1]);
      if (element.closed) context.closePath();
    }
    flush();
  }

  addLight(light) {
    if (light.isHemisphereLight) {
      this.lights.sky.add(light.color.clone().multiplyScalar(light.intensity));
      this.lights.ground.add(light.groundColor.clone().multiplyScalar(light.intensity));
    } else if (light.isDirectionalLight) {
      const direction = new THREE.Vector3().setFromMatrixPosition(light.matrixWorld)
        .sub(new THREE.Vector3().setFromMatrixPosition(light.target.matrixWorld)).normalize();
      this.lights.suns.push({ direction, color: light.color.clone().multiplyScalar(light.intensity) });
    }
  }

  // A point of the world on the canvas: [x, y] in CSS pixels and w, its depth from the camera.
  project(vector, into) {
    const e = this.viewProjection.elements;
    const x = vector.x, y = vector.y, z = vector.z;
    const w = e[3] * x + e[7] * y + e[11] * z + e[15];
    into.x = ((e[0] * x + e[4] * y + e[8] * z + e[12]) / w + 1) * this.width / 2;
    into.y = (1 - (e[1] * x + e[5] * y + e[9] * z + e[13]) / w) * this.height / 2;
    into.w = w;
    return into;
  }

  scratch(count) {
    while (this.world.length < count) {
      this.world.push(new THREE.Vector3());
      this.screen.push({ x: 0, y: 0, w: 0 });
    }
  }

  addMesh(mesh) {
    const geometry = mesh.geometry, material = mesh.material;
    if (!geometry.isGeometry) throw new Error("canvas 3D view: a mesh of BufferGeometry");
    this.scratch(geometry.vertices.length);
    geometry.vertices.forEach((vertex, i) => {
      this.world[i].copy(vertex).applyMatrix4(mesh.matrixWorld);
      this.project(this.world[i], this.screen[i]);
    });
    const lambert = material.isMeshLambertMaterial;
    const normal = new THREE.Vector3(), edge = new THREE.Vector3(), toCamera = new THREE.Vector3();
    for (const face of geometry.faces) {
      const a = this.screen[face.a], b = this.screen[face.b], c = this.screen[face.c];
      if (a.w <= 0 || b.w <= 0 || c.w <= 0) continue; // behind the camera
      const wa = this.world[face.a];
      normal.subVectors(this.world[face.c], this.world[face.b])
        .cross(edge.subVectors(wa, this.world[face.b])).normalize();
      if (normal.dot(toCamera.subVectors(this.cameraPosition, wa)) <= 0) continue; // its back
      const points = [a.x, a.y, b.x, b.y, c.x, c.y];
      grow(points);
      this.elements.push({
        depth: (a.w + b.w + c.w) / 3, order: mesh.renderOrder, points, fill: true, closed: true,
        style: cssColor(lambert ? this.lit(material.color, normal) : material.color, 1),
      });
    }
  }

  // Lambert shading of a face: its colour under the hemisphere and directional lights.
  lit(base, normal) {
    const light = this.lights.ground.clone().lerp(this.lights.sky, (normal.z + 1) / 2);
    for (const sun of this.lights.suns) {
      light.add(sun.color.clone().multiplyScalar(Math.max(0, normal.dot(sun.direction))));
    }
    const color = base.clone().multiply(light);
    return color.setRGB(Math.min(1, color.r), Math.min(1, color.g), Math.min(1, color.b));
  }

  addLine(line) {
    const geometry = line.geometry;
    const positions = geometry.getAttribute("position");
    const colors = geometry.getAttribute("color");
    const count = Math.min(positions.count, geometry.drawRange.count);
    const point = new THREE.Vector3();
    const screen = [];
    for (let i = 0; i < count; i++) {
      point.fromBufferAttribute(positions, i).applyMatrix4(line.matrixWorld);
      screen.push(this.project(point, { x: 0, y: 0, w: 0 }));
    }
    const material = line.material;
    const width = material.linewidth || 1;
    if (line.isLineSegments) {
      for (let i = 0; i + 1 < count; i += 2) {
        const color = colors
          ? new THREE.Color(colors.getX(i), colors.getY(i), colors.getZ(i)) : material.color;
        this.addRun(line, [screen[i], screen[i + 1]], color, width);
      }
      return;
    }
    // runs share their end points; drawn 2 px wide, to be seen over the faces' edges
    for (let start = 0; start + 1 < count; start += LINE_RUN) {
      this.addRun(line, screen.slice(start, start + LINE_RUN + 1), material.color, 2 * width);
    }
  }

  addRun(line, run, color, width) {
    if (run.some((point) => point.w <= 0)) return; // behind the camera
    const alpha = line.material.transparent ? line.material.opacity : 1;
    this.elements.push({
      depth: run.reduce((sum, point) => sum + point.w, 0) / run.length,
      order: line.renderOrder,
      style: cssColor(color, alpha),
      points: run.flatMap((point) => [point.x, point.y]),
      fill: false, width, closed: false,
    });
  }
}

// A triangle pushed out by half a pixel from its centre: filled triangles side by side
// otherwise show thin seams of the background between them (each edge is antialiased alone).
function grow(points) {
  const cx = (points[0] + points[2] + points[4]) / 3, cy = (points[1] + points[3] + points[5]) / 3;
  for (let i = 0; i < 6; i += 2) {
    const dx = points[i] - cx, dy = points[i + 1] - cy;
    const length = Math.hypot(dx, dy) || 1;
    points[i] += (dx / length) * 0.5;
    points[i + 1] += (dy / length) * 0.5;
  }
}

function cssColor(color, alpha) {
  const byte = (value) => Math.round(value * 255);
  return `rgba(${byte(color.r)},${byte(color.g)},${byte(color.b)},${alpha})`;
}

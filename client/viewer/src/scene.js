// The 3D view: the rig's target mesh from its GLB, posed by weights (morph targets on the
// GPU) or by whole vertex arrays. Knows nothing of sockets or the protocol.

import * as THREE from "three";
import { GLTFLoader } from "three/addons/loaders/GLTFLoader.js";
import { OrbitControls } from "three/addons/controls/OrbitControls.js";

import { applyMoving } from "./protocol.js";

export class FaceView {
  /** transparent: clear to alpha 0 (the overlay); controls: let the user orbit. */
  constructor(container, { transparent = false, controls = true, width = null, height = null } = {}) {
    this.container = container;
    this.fixedSize = width && height ? { width, height } : null;
    this.renderer = new THREE.WebGLRenderer({
      antialias: true,
      alpha: transparent,
      premultipliedAlpha: true,
      // Lets tests and the snapshot tool read the canvas back between frames.
      preserveDrawingBuffer: true,
    });
    this.renderer.setPixelRatio(Math.min(window.devicePixelRatio || 1, 2));
    this.renderer.outputColorSpace = THREE.SRGBColorSpace;
    if (transparent) this.renderer.setClearColor(0x000000, 0);
    else this.renderer.setClearColor(0x14161c, 1);
    container.appendChild(this.renderer.domElement);

    this.scene = new THREE.Scene();
    this.camera = new THREE.PerspectiveCamera(30, 1, 0.01, 1000);
    this.scene.add(new THREE.HemisphereLight(0xfff4ea, 0x40384a, 1.6));
    const key = new THREE.DirectionalLight(0xffffff, 2.2);
    key.position.set(0.6, 0.9, 1.2);
    this.scene.add(key);
    const rim = new THREE.DirectionalLight(0x9fc4ff, 1.2);
    rim.position.set(-1, 0.3, -0.8);
    this.scene.add(rim);

    this.controls = controls ? new OrbitControls(this.camera, this.renderer.domElement) : null;
    this.mesh = null;
    this.names = [];
    this.dirty = true;
    this.resize();
    window.addEventListener("resize", () => this.resize());
  }

  /** Parse a GLB (ArrayBuffer) and show its first morphed mesh; returns {names, vertexCount}. */
  async load(glb) {
    const gltf = await new Promise((resolve, reject) =>
      new GLTFLoader().parse(glb, "", resolve, (err) => reject(new Error(`model.glb: ${err.message || err}`))),
    );
    let mesh = null;
    gltf.scene.traverse((node) => {
      if (!mesh && node.isMesh) mesh = node;
    });
    if (!mesh) throw new Error("model.glb holds no mesh");
    const geometry = mesh.geometry;
    const morphs = geometry.morphAttributes.position || [];
    const names = mesh.userData.targetNames || [];
    if (names.length !== morphs.length) {
      throw new Error(`model.glb: ${morphs.length} morph targets but ${names.length} targetNames`);
    }
    addMorphNormals(geometry);
    mesh.material = new THREE.MeshStandardMaterial({
      color: 0xf0a070,
      roughness: 0.55,
      metalness: 0.0,
    });
    // Morphs move vertices outside the neutral's bounding sphere.
    mesh.frustumCulled = false;
    if (this.mesh) this.scene.remove(this.root);
    this.root = gltf.scene;
    this.scene.add(this.root);
    this.mesh = mesh;
    this.names = names;
    this.basePositions = geometry.attributes.position.array.slice();
    this.frame(geometry);
    this.dirty = true;
    return { names, vertexCount: geometry.attributes.position.count };
  }

  /** weights: Float32Array of M, in targetNames order (== the rig's weight order). */
  setWeights(weights) {
    const influences = this.mesh.morphTargetInfluences;
    if (weights.length !== influences.length) {
      throw new Error(`got ${weights.length} weights for ${influences.length} morph targets`);
    }
    for (let i = 0; i < weights.length; i++) influences[i] = weights[i];
    this.dirty = true;
  }

  /**
   * vertices: Float32Array of N*3, the vertices `moving` (Uint32Array) of an output
   * "moving" result; the others keep the neutral's positions.
   */
  setMovingVertices(moving, vertices) {
    const position = this.mesh.geometry.attributes.position;
    if (moving.length && moving[moving.length - 1] >= position.count) {
      throw new Error(`moving vertex ${moving[moving.length - 1]} is beyond a mesh of ${position.count}`);
    }
    this.mesh.morphTargetInfluences.fill(0);
    applyMoving(position.array, moving, vertices);
    position.needsUpdate = true;
    this.mesh.geometry.computeVertexNormals();
    this.dirty = true;
  }

  /** vertices: Float32Array of V*3, in the mesh's vertex order. */
  setVertices(vertices) {
    const position = this.mesh.geometry.attributes.position;
    if (vertices.length !== position.array.length) {
      throw new Error(`got ${vertices.length / 3} vertices for a mesh of ${position.count}`);
    }
    this.mesh.morphTargetInfluences.fill(0);
    position.array.set(vertices);
    position.needsUpdate = true;
    this.mesh.geometry.computeVertexNormals();
    this.dirty = true;
  }

  render() {
    if (this.controls) this.controls.update();
    this.renderer.render(this.scene, this.camera);
    this.dirty = false;
  }

  resize() {
    const width = this.fixedSize ? this.fixedSize.width : this.container.clientWidth || window.innerWidth;
    const height = this.fixedSize ? this.fixedSize.height : this.container.clientHeight || window.innerHeight;
    this.renderer.setSize(width, height);
    this.camera.aspect = width / height;
    this.camera.updateProjectionMatrix();
    this.dirty = true;
  }

  /** Put the camera in front of the face (+z out of the face, y up) so it fills the view. */
  frame(geometry) {
    // The neutral's bounds: three.js's own bounding sphere also takes in every morph
    // target at full weight, which makes the face small and off-centre.
    const box = new THREE.Box3().setFromBufferAttribute(geometry.attributes.position);
    const center = box.getCenter(new THREE.Vector3());
    const radius = box.getSize(new THREE.Vector3()).length() / 2;
    const fov = THREE.MathUtils.degToRad(this.camera.fov);
    // The face's bounding sphere fills ~85% of the shorter side of the view.
    const fit = Math.min(1, this.camera.aspect);
    const distance = radius / (0.85 * Math.tan(fov / 2) * fit);
    this.camera.position.set(center.x + 0.18 * distance, center.y + 0.1 * distance, center.z + distance);
    this.camera.near = distance / 100;
    this.camera.far = distance * 10;
    this.camera.updateProjectionMatrix();
    this.camera.lookAt(center);
    if (this.controls) {
      this.controls.target.copy(center);
      this.controls.update();
    }
  }
}

/**
 * Normal offsets per morph target, from each target's own vertex normals, so lighting
 * follows the expression (the GLB carries position targets only). Computed once here;
 * the GPU blends them with the same weights as the positions.
 */
function addMorphNormals(geometry) {
  const morphs = geometry.morphAttributes.position || [];
  if (!morphs.length || !geometry.attributes.normal) return;
  const base = geometry.attributes.normal.array;
  const scratch = new THREE.BufferGeometry();
  scratch.setIndex(geometry.index);
  const positions = geometry.attributes.position.array;
  const normals = morphs.map((target) => {
    const posed = new Float32Array(positions.length);
    for (let i = 0; i < posed.length; i++) posed[i] = positions[i] + target.array[i];
    scratch.setAttribute("position", new THREE.BufferAttribute(posed, 3));
    scratch.computeVertexNormals();
    const normal = scratch.attributes.normal.array;
    const delta = new Float32Array(normal.length);
    for (let i = 0; i < delta.length; i++) delta[i] = normal[i] - base[i];
    return new THREE.BufferAttribute(delta, 3);
  });
  geometry.morphAttributes.normal = normals;
}

// The 3D view: the rig's target mesh from its GLB, posed by weights (morph targets on the
// GPU) or by whole vertex arrays; or the rig's character file as uploaded (character.js),
// posed by weights through its bindings and by the head pose. Knows nothing of sockets or
// the protocol.

import * as THREE from "three";
import { GLTFLoader } from "three/addons/loaders/GLTFLoader.js";
import { OrbitControls } from "three/addons/controls/OrbitControls.js";

import { applyWeights, bindMorphs, findHead, headQuaternion, parseCharacter, springsMoving } from "./character.js";
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
    // What the canvas shows, for people and tests to synchronise on (characterState()):
    // none, loading, vrm or gltf (a character file), model (the rig's own mesh), error.
    this.setCharacterStatus("none");

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
    this.mesh = null; // the rig's mesh (model.glb); null while a character is shown
    this.character = null; // {vrm, bound, head, headRest, format} for a character file
    this.loaded = false;
    this.clock = new THREE.Clock();
    this.names = [];
    // Whether the picture is out of date: set by a pose that changes what is drawn, not by
    // one equal to the pose on screen (a still face, a repeated frame: an idle page draws
    // nothing, docs/viewer.md).
    this.dirty = true;
    this.lastVertices = null; // the last vertex output applied (setVertices, setMovingVertices)
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
    this.show(gltf.scene);
    this.setCharacterStatus("model");
    this.mesh = mesh;
    this.names = names;
    this.basePositions = geometry.attributes.position.array.slice();
    // The neutral's bounds: three.js's own bounding sphere also takes in every morph
    // target at full weight, which makes the face small and off-centre.
    this.frame(new THREE.Box3().setFromBufferAttribute(geometry.attributes.position));
    this.dirty = true;
    return { names, vertexCount: geometry.attributes.position.count };
  }

  /**
   * Show a character file (ArrayBuffer of its GLB; a VRM is one) as authored, posed
   * through `character.bindings` (GET /v1/rigs/{id}'s `character`: per rig weight, the
   * {mesh, morph, weight} it drives). Framed on the meshes the bindings drive (the face).
   */
  async loadCharacter(glb, character) {
    this.setCharacterStatus("loading");
    let parsed;
    try {
      parsed = await parseCharacter(glb, { format: character.format });
    } catch (err) {
      this.setCharacterStatus("error");
      throw err;
    }
    const { root, vrm, meshesByIndex, vrmError } = parsed;
    this.show(root);
    this.mesh = null;
    const bound = bindMorphs(meshesByIndex, character.bindings || []);
    const head = findHead(root, vrm);
    this.character = {
      vrm,
      bound,
      head,
      headRest: head ? head.quaternion.clone() : null,
      format: character.format,
      weights: null,
      vrmError,
    };
    // The eyes look at the viewer: three-vrm's look-at aims them at the camera on every
    // vrm.update (bone or expression look-at, within the file's range maps).
    if (vrm && vrm.lookAt) vrm.lookAt.target = this.camera;
    if (vrm) vrm.update(0);
    root.updateMatrixWorld(true);
    const box = new THREE.Box3();
    const driven = new Set();
    for (const list of character.bindings || []) for (const { mesh } of list) driven.add(mesh);
    for (const index of driven) for (const object of meshesByIndex.get(index) || []) box.expandByObject(object);
    this.frame(box.isEmpty() ? new THREE.Box3().setFromObject(root) : box);
    this.dirty = true;
    this.setCharacterStatus(vrm ? "vrm" : "gltf");
    return {
      meshes: meshesByIndex.size,
      vrm: Boolean(vrm),
      bound: bound.slots.length,
      head: head ? head.name : null,
      vrmError,
      materials: materialTypes(root),
    };
  }

  /** Mark the canvas (`data-character`) with what it shows (see the constructor). */
  setCharacterStatus(status) {
    this.renderer.domElement.dataset.character = status;
  }

  /**
   * What the character shown is and how it is posed now, for tests and the curious
   * (window.characterState()): its meshes (with their vertex counts as decoded) and morph
   * targets, which of three-vrm's parts exist, the head bone's rotation, where the eyes
   * look, the morph influences in effect.
   */
  characterState() {
    const c = this.character;
    const state = { status: this.renderer.domElement.dataset.character, format: null, meshes: [], morphs: 0 };
    if (!c) return state;
    state.format = c.format;
    state.vrmError = c.vrmError;
    const influences = {};
    this.root.updateMatrixWorld(true);
    this.root.traverse((node) => {
      if (!node.isMesh) return;
      const weights = node.morphTargetInfluences || [];
      const vertices = node.geometry.attributes.position ? node.geometry.attributes.position.count : 0;
      state.meshes.push({ name: node.name, morphs: weights.length, skinned: Boolean(node.isSkinnedMesh), vertices });
      state.morphs += weights.length;
      const names = Object.entries(node.morphTargetDictionary || {});
      for (const [name, index] of names) {
        if (weights[index] > 1e-4) (influences[node.name] ||= {})[name] = weights[index];
      }
    });
    state.influences = influences;
    if (c.head) {
      const world = c.head.getWorldQuaternion(new THREE.Quaternion());
      state.head = { name: c.head.name, rotation: c.head.quaternion.toArray(), world: world.toArray() };
    } else {
      state.head = null;
    }
    const vrm = c.vrm;
    if (vrm) {
      const springs = vrm.springBoneManager;
      state.vrm = {
        metaVersion: vrm.meta ? vrm.meta.metaVersion : null,
        humanoid: Boolean(vrm.humanoid),
        humanBones: vrm.humanoid ? Object.keys(vrm.humanoid.humanBones).sort() : [],
        lookAt: Boolean(vrm.lookAt),
        expressionManager: Boolean(vrm.expressionManager),
        expressions: vrm.expressionManager ? vrm.expressionManager.expressions.map((e) => e.expressionName) : [],
        springBoneManager: Boolean(springs),
        springJoints: springs ? springs.joints.size : 0,
        springsSettled: Boolean(c.springsSettled),
        firstPerson: Boolean(vrm.firstPerson),
      };
      if (vrm.lookAt) {
        state.lookAt = {
          target: vrm.lookAt.target === this.camera ? "camera" : vrm.lookAt.target ? "object" : null,
          yaw: vrm.lookAt.yaw,
          pitch: vrm.lookAt.pitch,
        };
      }
    } else {
      state.vrm = null;
    }
    return state;
  }

  show(root) {
    if (this.root) this.scene.remove(this.root);
    this.lastVertices = null; // nothing of the last model's pose is on screen
    this.root = root;
    this.scene.add(root);
    this.character = null;
    this.loaded = true;
  }

  /** rotation: the head pose's (x, y, z, w) (PROTOCOL.md §5.3); turns the head bone. */
  setHead(rotation) {
    const c = this.character;
    if (!c || !c.head) return;
    const q = headQuaternion(rotation);
    // A VRM 0.x model faces -z in its own frame (turned about y to face the camera).
    if (c.format === "vrm0") q.set(-q.x, q.y, -q.z, q.w);
    if (!c.vrm) q.premultiply(c.headRest);
    if (q.equals(c.head.quaternion)) return;
    c.head.quaternion.copy(q);
    this.dirty = true;
  }

  /**
   * Match the rig's weight names (its `ready`) to the morph targets by name: the GLB leaves
   * out targets that move nothing (the neutral). False when a target has no weight, i.e.
   * the model is not this rig's.
   */
  bindWeights(names) {
    if (this.character) {
      // The bindings come in the rig's weight order: one list per weight.
      this.weightCount = this.character.bound.perWeight.length;
      return names.length === this.weightCount;
    }
    const index = new Map(names.map((name, i) => [name, i]));
    const order = this.names.map((name) => index.get(name));
    if (order.some((i) => i === undefined)) return false;
    this.weightOrder = order;
    this.weightCount = names.length;
    return true;
  }

  /** weights: Float32Array of M, in the rig's weight order (see bindWeights). */
  setWeights(weights) {
    if (this.character) {
      if (weights.length !== this.character.bound.perWeight.length) {
        throw new Error(`got ${weights.length} weights for a character bound to ${this.character.bound.perWeight.length}`);
      }
      const previous = this.character.weights;
      if (previous && sameValues(previous, weights)) return;
      this.character.weights = weights.slice(); // a copy: the caller's array may be reused
      applyWeights(this.character.bound, weights);
      this.dirty = true;
      return;
    }
    const influences = this.mesh.morphTargetInfluences;
    const order = this.weightOrder;
    if (!order || weights.length !== this.weightCount) {
      throw new Error(`got ${weights.length} weights for a rig of ${this.weightCount ?? "unknown"}`);
    }
    for (let j = 0; j < order.length; j++) {
      const w = weights[order[j]];
      if (influences[j] === w) continue;
      influences[j] = w;
      this.dirty = true;
    }
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
    if (this.unchanged(vertices)) return;
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
    if (this.unchanged(vertices)) return;
    this.mesh.morphTargetInfluences.fill(0);
    position.array.set(vertices);
    position.needsUpdate = true;
    this.mesh.geometry.computeVertexNormals();
    this.dirty = true;
  }

  /** Whether a vertex output equals the last one applied (kept for the next call). */
  unchanged(vertices) {
    const same = this.lastVertices !== null && sameValues(this.lastVertices, vertices);
    if (!same) this.lastVertices = vertices.slice(); // a copy: the caller's array may be reused
    return same;
  }

  /**
   * The rig's mesh as posed now (window.facecastApplied()): `positions`, its V*3 vertex
   * positions (the neutral's until vertices are applied), and `influences`, its morph
   * targets' weights by name; {} while a character file is shown instead.
   */
  meshState() {
    if (!this.mesh) return {};
    const influences = {};
    this.names.forEach((name, j) => (influences[name] = this.mesh.morphTargetInfluences[j]));
    return { positions: Array.from(this.mesh.geometry.attributes.position.array), influences };
  }

  render() {
    if (this.controls) this.controls.update();
    const c = this.character;
    const delta = this.clock.getDelta();
    if (c && c.vrm) {
      // three-vrm's update (look-at, spring bones, normalised bones to the skeleton)
      // resets the morphs its expressions bind: the rig's weights go on after it.
      c.vrm.update(Math.min(delta, 0.1));
      if (c.weights) applyWeights(c.bound, c.weights);
    }
    this.renderer.render(this.scene, this.camera);
    // Spring bones keep moving after the pose stops changing: drawn again until they
    // settle (an idle overlay then costs nothing, as for any other character).
    const springs = c && c.vrm && c.vrm.springBoneManager ? c.vrm.springBoneManager.joints : null;
    if (springs && springs.size) {
      c.springPose ||= new Float32Array(springs.size * 4);
      c.springsSettled = !springsMoving(springs, c.springPose);
      this.dirty = !c.springsSettled;
    } else {
      this.dirty = false;
    }
  }

  resize() {
    const width = this.fixedSize ? this.fixedSize.width : this.container.clientWidth || window.innerWidth;
    const height = this.fixedSize ? this.fixedSize.height : this.container.clientHeight || window.innerHeight;
    this.renderer.setSize(width, height);
    this.camera.aspect = width / height;
    this.camera.updateProjectionMatrix();
    // Without controls (the overlay) nobody moves the camera: frame again for the new shape.
    if (!this.controls && this.framed) this.frame(this.framed);
    this.dirty = true;
  }

  /**
   * Put the camera in front of the face (+z out of the face, y up, a little from the right
   * and above) so `box` (the neutral's, or the character face's), as drawn, fills
   * FRAME_FILL of the view's shorter side.
   */
  frame(box) {
    const center = box.getCenter(new THREE.Vector3());
    const size = box.getSize(new THREE.Vector3());
    const direction = new THREE.Vector3(0.18, 0.1, 1).normalize();
    // Start from the distance at which the bounding sphere fills the view, then scale it by
    // how much of the view the projected box really takes (a sphere around a flat face or
    // a tall head is far larger than either): drawn size goes as 1 / distance, so a few
    // rounds settle it to within a pixel.
    const fov = THREE.MathUtils.degToRad(this.camera.fov);
    let distance = size.length() / 2 / (Math.tan(fov / 2) * Math.min(1, this.camera.aspect));
    for (let round = 0; round < 4; round++) {
      this.placeCamera(center, direction, distance);
      distance *= projectedFill(box, this.camera) / FRAME_FILL;
    }
    this.placeCamera(center, direction, distance);
    this.framed = box;
    if (this.controls) {
      this.controls.target.copy(center);
      this.controls.update();
    }
  }

  placeCamera(center, direction, distance) {
    this.camera.position.copy(center).addScaledVector(direction, distance);
    this.camera.near = distance / 100;
    this.camera.far = distance * 10;
    this.camera.lookAt(center);
    this.camera.updateProjectionMatrix();
    this.camera.updateMatrixWorld();
  }
}

/** The kinds of material the character is drawn with (MToonMaterial for a VRM's MToon). */
function materialTypes(root) {
  const types = new Set();
  root.traverse((node) => {
    if (!node.isMesh) return;
    for (const material of [].concat(node.material)) types.add(material.isMToonMaterial ? "MToonMaterial" : material.type);
  });
  return [...types].sort();
}

/** Share of the shorter side the neutral's box corners take: its silhouette then fills ~65-75 %. */
const FRAME_FILL = 0.8;

/** The larger side of a box's drawn extent over the view's shorter side (1 = it just fits). */
function projectedFill(box, camera) {
  const corner = new THREE.Vector3();
  let minX = Infinity;
  let maxX = -Infinity;
  let minY = Infinity;
  let maxY = -Infinity;
  for (let i = 0; i < 8; i++) {
    corner.set(i & 1 ? box.max.x : box.min.x, i & 2 ? box.max.y : box.min.y, i & 4 ? box.max.z : box.min.z);
    corner.project(camera);
    minX = Math.min(minX, corner.x);
    maxX = Math.max(maxX, corner.x);
    minY = Math.min(minY, corner.y);
    maxY = Math.max(maxY, corner.y);
  }
  // Normalised device coordinates span 2 across the width and 2 across the height.
  const width = ((maxX - minX) / 2) * camera.aspect;
  const height = (maxY - minY) / 2;
  return Math.max(width, height) / Math.min(1, camera.aspect);
}

/**
 * Normal offsets per morph target, from each target's own vertex normals, so lighting
 * follows the expression; only for GLBs that carry position targets alone (facecast's own
 * carry NORMAL offsets too). Computed once here; the GPU blends them with the same
 * weights as the positions.
 */
function addMorphNormals(geometry) {
  const morphs = geometry.morphAttributes.position || [];
  if (!morphs.length || !geometry.attributes.normal) return;
  if ((geometry.morphAttributes.normal || []).length === morphs.length) return;
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

/** Whether two arrays of numbers hold the same values. */
function sameValues(a, b) {
  if (a.length !== b.length) return false;
  for (let i = 0; i < a.length; i++) if (a[i] !== b[i]) return false;
  return true;
}

// A character as its author made it: the uploaded glTF/VRM (all meshes, materials,
// textures, skinning; VRM through @pixiv/three-vrm), posed by the rig's weights through
// the server's bindings (morph targets on every bound mesh, on the GPU) and by the head
// pose (the head bone). Knows nothing of sockets or the protocol.

import * as THREE from "three";
import { DRACOLoader } from "three/addons/loaders/DRACOLoader.js";
import { GLTFLoader } from "three/addons/loaders/GLTFLoader.js";
import { MeshoptDecoder } from "three/addons/libs/meshopt_decoder.module.js";
import { VRMLoaderPlugin, VRMUtils } from "@pixiv/three-vrm";

// Compressed files (KHR_draco_mesh_compression, EXT_meshopt_compression) are decoded by
// three.js's own decoders, served by facecast: Draco's from /viewer/assets/draco/ (copied
// out of three's examples/jsm/libs/draco/gltf by build.mjs; relative, so the pages work
// under a proxy's prefix too), meshoptimizer's bundled into this script.
// KHR_mesh_quantization needs no decoder. One DRACOLoader (its workers) for every file.
export const DRACO_PATH = "viewer/assets/draco/";
let draco = null;

function parse(glb, withVrm) {
  const loader = new GLTFLoader();
  draco ||= new DRACOLoader().setDecoderPath(DRACO_PATH);
  loader.setDRACOLoader(draco);
  loader.setMeshoptDecoder(MeshoptDecoder);
  if (withVrm) loader.register((parser) => new VRMLoaderPlugin(parser));
  return new Promise((resolve, reject) =>
    loader.parse(glb, "", resolve, (err) => reject(new Error(`character.glb: ${err.message || err}`))),
  );
}

/**
 * Parse the character's GLB (ArrayBuffer): {root, vrm, meshesByIndex, vrmError}. A VRM
 * three-vrm refuses (a humanoid missing required bones, say) is shown as plain glTF, its
 * meshes, materials and skin as they are, with three-vrm's reason in `vrmError`.
 */
export async function parseCharacter(glb, { format = "gltf" } = {}) {
  const withVrm = format !== "gltf";
  let gltf;
  let vrmError = null;
  try {
    gltf = await parse(glb, withVrm);
  } catch (err) {
    if (!withVrm) throw err;
    vrmError = err.message;
    gltf = await parse(glb, false);
  }
  const vrm = gltf.userData.vrm || null;
  const root = vrm ? vrm.scene : gltf.scene;
  // VRM 0.x faces -z; turned about y so that every character faces the camera (+z) alike
  // (three-vrm's rotateVRM0, by hand when three-vrm refused the file).
  if (vrm && vrm.meta && vrm.meta.metaVersion === "0") VRMUtils.rotateVRM0(vrm);
  else if (!vrm && format === "vrm0") root.rotation.y = Math.PI;
  // The bindings name meshes by their index in the file's `meshes`: the loader's
  // associations give the three.js meshes (one per primitive) each index became.
  const meshesByIndex = new Map();
  root.traverse((node) => {
    if (!node.isMesh) return;
    const association = gltf.parser.associations.get(node);
    if (!association || association.meshes === undefined) return;
    if (!meshesByIndex.has(association.meshes)) meshesByIndex.set(association.meshes, []);
    meshesByIndex.get(association.meshes).push(node);
    // three.js names morphs from mesh.extras.targetNames only; many exporters put them on
    // the primitive (as the server's reader accepts): name them from there too.
    const names = primitiveTargetNames(gltf.parser.json, association);
    if (names && node.morphTargetInfluences && names.length === node.morphTargetInfluences.length) {
      node.morphTargetDictionary = Object.fromEntries(names.map((name, index) => [name, index]));
    }
    // Morphs and skinning move vertices outside the rest pose's bounds.
    node.frustumCulled = false;
  });
  return { root, vrm, meshesByIndex, vrmError };
}

/**
 * The morph target names of the primitive `association` ({meshes, primitives}, the
 * loader's) when only a primitive carries them (`primitives[i].extras.targetNames`, else
 * the first primitive's), as the server's reader takes them; null when the mesh itself
 * names them (three.js did) or nothing does.
 */
export function primitiveTargetNames(json, association) {
  const mesh = (json.meshes || [])[association.meshes];
  if (!mesh || (mesh.extras && Array.isArray(mesh.extras.targetNames))) return null;
  const primitives = mesh.primitives || [];
  for (const primitive of [primitives[association.primitives ?? 0], primitives[0]]) {
    const names = primitive && primitive.extras && primitive.extras.targetNames;
    if (Array.isArray(names) && names.every((name) => typeof name === "string")) return names;
  }
  return null;
}

/**
 * bindings: one list of {mesh, morph, weight} per rig weight (GET /v1/rigs/{id}'s
 * `character.bindings`), in the rig's weight order. Returns the morph slots to drive:
 * per weight, [influences array, morph index, factor] triples; and every slot once.
 */
export function bindMorphs(meshesByIndex, bindings) {
  const slots = new Map(); // "meshObjectId:morph" -> [influences, morph]
  const perWeight = bindings.map((list) =>
    list.flatMap(({ mesh, morph, weight }) =>
      (meshesByIndex.get(mesh) || [])
        .filter((object) => object.morphTargetInfluences && morph < object.morphTargetInfluences.length)
        .map((object) => {
          const key = `${object.id}:${morph}`;
          if (!slots.has(key)) slots.set(key, [object.morphTargetInfluences, morph]);
          return [object.morphTargetInfluences, morph, weight];
        }),
    ),
  );
  return { perWeight, slots: [...slots.values()] };
}

/** Write weights into the bound morph targets: sum of weight × binding factor per slot. */
export function applyWeights(bound, weights) {
  for (const [influences, morph] of bound.slots) influences[morph] = 0;
  const { perWeight } = bound;
  for (let j = 0; j < perWeight.length; j++) {
    const w = weights[j];
    if (!w) continue;
    for (const [influences, morph, factor] of perWeight[j]) influences[morph] += w * factor;
  }
}

/**
 * The head pose of PROTOCOL.md §5.3 (x, y, z, w in VMC's left-handed frame, +x the
 * performer's right) as a three.js rotation of a character facing +z (+x its left):
 * mirrored in x, a turn about y or z changes sign.
 */
export function headQuaternion(rotation, out = new THREE.Quaternion()) {
  const [x, y, z, w] = rotation;
  return out.set(x, -y, -z, w).normalize();
}

/** The head bone to turn: the VRM's normalised head, else the first bone named like a head. */
export function findHead(root, vrm) {
  if (vrm && vrm.humanoid) {
    const head = vrm.humanoid.getNormalizedBoneNode("head");
    if (head) return head;
  }
  let found = null;
  root.traverse((node) => {
    if (!found && (node.isBone || node.type === "Object3D") && /^(j_bip_c_)?head$/i.test(node.name)) found = node;
  });
  if (!found) {
    root.traverse((node) => {
      if (!found && node.isBone && /head/i.test(node.name) && !/top|end/i.test(node.name)) found = node;
    });
  }
  return found;
}

/** "name · by authors · licence (no redistribution)" from the server's normalised meta. */
export function metaText(meta, format) {
  if (!meta || !Object.keys(meta).length) return format === "gltf" ? "" : format.toUpperCase();
  const parts = [];
  if (meta.name) parts.push(meta.name);
  if (meta.authors && meta.authors.length) parts.push(`by ${meta.authors.join(", ")}`);
  if (meta.licence || meta.licence_url) parts.push(`licence ${meta.licence || meta.licence_url}`);
  if (meta.redistribution === false) parts.push("no redistribution");
  return `${format === "vrm0" ? "VRM 0.x" : format === "vrm1" ? "VRM 1.0" : "glTF"} · ${parts.join(" · ")}`;
}

/**
 * Whether spring bones still move: the largest change of a spring joint's rotation since
 * the last call (kept in `last`, a Float32Array of 4 per joint) above `tolerance`. Once
 * they settle the page stops redrawing until something else changes (a pose, the camera).
 */
export function springsMoving(joints, last, tolerance = 1e-5) {
  let moved = 0;
  let i = 0;
  for (const joint of joints) {
    const q = joint.bone.quaternion;
    moved = Math.max(moved, Math.abs(q.x - last[i]), Math.abs(q.y - last[i + 1]), Math.abs(q.z - last[i + 2]), Math.abs(q.w - last[i + 3]));
    last[i] = q.x;
    last[i + 1] = q.y;
    last[i + 2] = q.z;
    last[i + 3] = q.w;
    i += 4;
  }
  return moved > tolerance;
}

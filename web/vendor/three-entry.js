// The parts of three.js the what-if view uses; bundled and minified into three.min.js by
// web/vendor/README.md's command (esbuild drops everything not named here).
export {
  Box3, Box3Helper, BufferAttribute, BufferGeometry, Color, Group, Mesh, MeshBasicMaterial,
  PerspectiveCamera, Points, PointsMaterial, Scene, SphereGeometry, Vector3, WebGLRenderer, ArrowHelper,
} from "three";
export { OrbitControls } from "three/examples/jsm/controls/OrbitControls.js";

// The Khronos glTF validator on one .glb/.gltf: prints its issues report as JSON (numErrors,
// numWarnings, messages). `make setup` installs the validator into .venv/node where npm exists.
const path = require('path');
const validator = require(path.join(__dirname, '..', '.venv', 'node', 'node_modules', 'gltf-validator'));
const fs = require('fs');

const data = new Uint8Array(fs.readFileSync(process.argv[2]));
validator.validateBytes(data)
  .then((report) => { console.log(JSON.stringify(report.issues)); })
  .catch((err) => { console.error(String(err)); process.exit(1); });

// Validate one glTF/GLB file with the Khronos glTF-Validator; print its issue counts and messages as JSON.
const fs = require('fs');
const validator = require('gltf-validator');

const data = new Uint8Array(fs.readFileSync(process.argv[2]));
validator.validateBytes(data).then((report) => {
  const i = report.issues;
  console.log(JSON.stringify({errors: i.numErrors, warnings: i.numWarnings, infos: i.numInfos, hints: i.numHints,
    messages: i.messages}));
}).catch((e) => { console.error(String(e)); process.exit(2); });

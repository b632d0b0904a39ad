#!/usr/bin/env node
// Validates glTF files with the Khronos glTF-Validator (npm package `gltf-validator`).
//
//   node validate.mjs FILE...
//
// Prints, per file, the counts of errors, warnings, infos and hints and the message of every
// error, warning and info. Exits 1 if any file has an error or cannot be read or validated,
// 2 on bad usage or when the validator package is missing.
import { readFile } from 'node:fs/promises';
import { basename } from 'node:path';

const SEVERITY = ['error', 'warning', 'info', 'hint'];

const files = process.argv.slice(2);
if (files.length === 0) {
  console.error('usage: node validate.mjs FILE...');
  process.exit(2);
}

let validator;
try {
  validator = await import('gltf-validator');
} catch (e) {
  console.error(`cannot load gltf-validator (npm install gltf-validator): ${e.message}`);
  process.exit(2);
}
const validateBytes = validator.validateBytes ?? validator.default?.validateBytes;

let failed = false;
for (const file of files) {
  let report;
  try {
    const bytes = new Uint8Array(await readFile(file));
    report = await validateBytes(bytes, {
      uri: basename(file),
      maxIssues: 0, // unlimited
      writeTimestamp: false,
      // The samples embed their buffers as data: URIs; anything external is refused so that a
      // file that depends on other files does not pass unchecked.
      externalResourceFunction: (uri) => Promise.reject(new Error(`external resource ${uri}`)),
    });
  } catch (e) {
    console.log(`${file}: FAILED to validate: ${e?.message ?? e}`);
    failed = true;
    continue;
  }
  const { numErrors, numWarnings, numInfos, numHints, messages } = report.issues;
  console.log(
    `${file}: ${numErrors} errors, ${numWarnings} warnings, ${numInfos} infos, ${numHints} hints`,
  );
  for (const m of messages) {
    if (m.severity <= 2) {
      console.log(`  ${SEVERITY[m.severity]} ${m.code} ${m.pointer ?? ''}: ${m.message}`);
    }
  }
  if (numErrors > 0) failed = true;
}
process.exit(failed ? 1 : 0);

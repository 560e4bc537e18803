// Validates KEDA ScaledObjects against KEDA's CRD schema (the npm package
// @kubernetes-models/keda). scripts/check-deploy.sh copies this file beside its node_modules
// and runs it: `node validate-keda.mjs FILE...`; exit status 1 on any invalid object.
import fs from 'node:fs';
import yaml from 'js-yaml';
import { ScaledObject } from '@kubernetes-models/keda/keda.sh/v1alpha1';

let failed = 0;
let checked = 0;
for (const file of process.argv.slice(2)) {
  for (const doc of yaml.loadAll(fs.readFileSync(file, 'utf8'))) {
    if (!doc) continue;
    const name = `${file}: ${doc.kind}/${doc.metadata?.name}`;
    if (doc.kind !== 'ScaledObject') {
      failed++;
      console.error(`${name}: expected only ScaledObjects here`);
      continue;
    }
    try {
      new ScaledObject(doc).validate();
      checked++;
    } catch (e) {
      failed++;
      console.error(`${name}: ${e.message}`);
    }
  }
}
console.log(`KEDA: ${checked} ScaledObject(s) valid, ${failed} invalid`);
process.exit(failed || !checked ? 1 : 0);

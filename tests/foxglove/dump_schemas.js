// Writes every JSON Schema that @foxglove/schemas exports (Foxglove's own, published on
// npm) to DIR/<Name>.json, for tests/services/test_foxglove.py to validate against.
// Run by `make foxglove-schemas` (a dependency of `make test`): node dump_schemas.js DIR
const fs = require("fs");
const path = require("path");
const dir = process.argv[2];
const schemas = require(path.resolve(dir, "..", "node_modules", "@foxglove", "schemas", "jsonschema"));
fs.mkdirSync(dir, { recursive: true });
for (const [name, schema] of Object.entries(schemas)) {
  fs.writeFileSync(path.join(dir, name + ".json"), JSON.stringify(schema, null, 2) + "\n");
}
const version = require(path.resolve(dir, "..", "node_modules", "@foxglove", "schemas", "package.json")).version;
fs.writeFileSync(path.join(dir, "VERSION"), version + "\n");
console.log(`@foxglove/schemas ${version}: ${Object.keys(schemas).length} JSON Schemas in ${dir}`);

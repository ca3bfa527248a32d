//! The glTF document checked before the gltf crate parses it: the GLB
//! container's lengths, and every index one element holds into another
//! (accessors, buffer views, buffers, meshes, nodes, ...), which the
//! crate's own validation follows without checking (a POSITION accessor
//! index past the accessors once panicked inside it, and a GLB length
//! under its 12-byte header asked for a 4 GiB buffer).

use serde_json::Value;

/// The JSON of a `.gltf` file, or of a GLB container's first chunk, once
/// the container's lengths are checked. Err: why not, and where.
pub(super) fn json_of(bytes: &[u8]) -> Result<&[u8], (String, String)> {
    if !bytes.starts_with(b"glTF") {
        return Ok(bytes);
    }
    let word = |at: usize| {
        bytes
            .get(at..at + 4)
            .map(|b| u32::from_le_bytes(b.try_into().expect("4 bytes")) as usize)
    };
    let bad = |what: &str| Err(("GLB header".to_string(), what.to_string()));
    let (Some(version), Some(length)) = (word(4), word(8)) else {
        return bad("the file ends inside its 12-byte header");
    };
    if version != 2 {
        return bad(&format!("version {version}; only glTF 2 is read"));
    }
    if length < 20 || length > bytes.len() {
        return bad(&format!(
            "a length of {length} bytes, for a file of {} bytes",
            bytes.len()
        ));
    }
    let (Some(chunk), Some(kind)) = (word(12), word(16)) else {
        return bad("no first chunk");
    };
    if kind != 0x4E4F_534A {
        return bad("the first chunk is not JSON");
    }
    if chunk > length - 20 {
        return bad(&format!(
            "a JSON chunk of {chunk} bytes past the container's {length}"
        ));
    }
    Ok(&bytes[20..20 + chunk])
}

/// Every index the document `root` holds names an element that exists.
/// Err: the element holding the first one that does not, and why.
pub(super) fn check_indices(root: &Value) -> Result<(), (String, String)> {
    let count = |k: &str| root.get(k).and_then(Value::as_array).map_or(0, Vec::len);
    let each = |k: &str| {
        root.get(k)
            .and_then(Value::as_array)
            .into_iter()
            .flatten()
            .enumerate()
    };
    let mut refs: Vec<(String, Option<&Value>, &str)> = Vec::new();
    for (i, m) in each("meshes") {
        let prims = m.get("primitives").and_then(Value::as_array);
        for (p, prim) in prims.into_iter().flatten().enumerate() {
            let at = format!("meshes[{i}].primitives[{p}]");
            let targets = prim.get("targets").and_then(Value::as_array);
            let maps = prim
                .get("attributes")
                .into_iter()
                .chain(targets.into_iter().flatten());
            for map in maps.filter_map(Value::as_object) {
                for (name, v) in map {
                    refs.push((format!("{at}.attributes.{name}"), Some(v), "accessors"));
                }
            }
            refs.push((format!("{at}.indices"), prim.get("indices"), "accessors"));
            refs.push((format!("{at}.material"), prim.get("material"), "materials"));
        }
    }
    for (i, a) in each("accessors") {
        refs.push((
            format!("accessors[{i}].bufferView"),
            a.get("bufferView"),
            "bufferViews",
        ));
        let sparse = a.get("sparse");
        for part in ["indices", "values"] {
            let v = sparse
                .and_then(|s| s.get(part))
                .and_then(|p| p.get("bufferView"));
            refs.push((format!("accessors[{i}].sparse.{part}"), v, "bufferViews"));
        }
    }
    for (i, v) in each("bufferViews") {
        refs.push((
            format!("bufferViews[{i}].buffer"),
            v.get("buffer"),
            "buffers",
        ));
    }
    for (i, n) in each("nodes") {
        refs.push((format!("nodes[{i}].mesh"), n.get("mesh"), "meshes"));
        refs.push((format!("nodes[{i}].camera"), n.get("camera"), "cameras"));
        refs.push((format!("nodes[{i}].skin"), n.get("skin"), "skins"));
        for c in n
            .get("children")
            .and_then(Value::as_array)
            .into_iter()
            .flatten()
        {
            refs.push((format!("nodes[{i}].children"), Some(c), "nodes"));
        }
    }
    for (i, s) in each("scenes") {
        for c in s
            .get("nodes")
            .and_then(Value::as_array)
            .into_iter()
            .flatten()
        {
            refs.push((format!("scenes[{i}].nodes"), Some(c), "nodes"));
        }
    }
    refs.push(("scene".into(), root.get("scene"), "scenes"));
    for (i, s) in each("skins") {
        refs.push((
            format!("skins[{i}].inverseBindMatrices"),
            s.get("inverseBindMatrices"),
            "accessors",
        ));
        refs.push((format!("skins[{i}].skeleton"), s.get("skeleton"), "nodes"));
        for j in s
            .get("joints")
            .and_then(Value::as_array)
            .into_iter()
            .flatten()
        {
            refs.push((format!("skins[{i}].joints"), Some(j), "nodes"));
        }
    }
    for (i, t) in each("textures") {
        refs.push((format!("textures[{i}].source"), t.get("source"), "images"));
        refs.push((
            format!("textures[{i}].sampler"),
            t.get("sampler"),
            "samplers",
        ));
    }
    for (i, im) in each("images") {
        refs.push((
            format!("images[{i}].bufferView"),
            im.get("bufferView"),
            "bufferViews",
        ));
    }
    for (i, a) in each("animations") {
        let samplers = a.get("samplers").and_then(Value::as_array);
        for (s, smp) in samplers.into_iter().flatten().enumerate() {
            for k in ["input", "output"] {
                refs.push((
                    format!("animations[{i}].samplers[{s}].{k}"),
                    smp.get(k),
                    "accessors",
                ));
            }
        }
        let channels = a.get("channels").and_then(Value::as_array);
        for (c, ch) in channels.into_iter().flatten().enumerate() {
            let node = ch.get("target").and_then(|t| t.get("node"));
            refs.push((
                format!("animations[{i}].channels[{c}].target.node"),
                node,
                "nodes",
            ));
            let n = samplers.map_or(0, Vec::len) as u64;
            if let Some(s) = ch
                .get("sampler")
                .and_then(Value::as_u64)
                .filter(|&s| s >= n)
            {
                let why = format!("sampler {s}, but the animation has {n}");
                return Err((format!("animations[{i}].channels[{c}].sampler"), why));
            }
        }
    }
    for (at, v, target) in refs {
        let Some(v) = v else { continue };
        let n = count(target) as u64;
        match v.as_u64() {
            Some(k) if k < n => {}
            _ => return Err((at, format!("index {v} names none of the {n} {target}"))),
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn indices_past_their_arrays_are_named() {
        let ok = br#"{"asset":{"version":"2.0"},"accessors":[{"count":3}],
            "meshes":[{"primitives":[{"attributes":{"POSITION":0}}]}],"nodes":[{"mesh":0}]}"#;
        let parse = |d: &[u8]| serde_json::from_slice::<Value>(d).unwrap();
        assert_eq!(check_indices(&parse(ok)), Ok(()));
        let cases = [
            (
                r#"{"meshes":[{"primitives":[{"attributes":{"POSITION":9}}]}]}"#,
                "meshes[0].primitives[0].attributes.POSITION",
            ),
            (
                r#"{"accessors":[{"bufferView":-1}]}"#,
                "accessors[0].bufferView",
            ),
            (r#"{"nodes":[{"children":[0, 1]}]}"#, "nodes[0].children"),
            (r#"{"scene":0}"#, "scene"),
            (
                r#"{"bufferViews":[{"buffer":"0"}]}"#,
                "bufferViews[0].buffer",
            ),
        ];
        for (doc, at) in cases {
            let (where_, why) = check_indices(&parse(doc.as_bytes())).unwrap_err();
            assert_eq!(where_, at, "{why}");
        }
    }

    #[test]
    fn glb_lengths_are_checked() {
        let json = br#"{"asset":{"version":"2.0"}}    "#;
        let mut glb = b"glTF".to_vec();
        glb.extend(2u32.to_le_bytes());
        glb.extend(((20 + json.len()) as u32).to_le_bytes());
        glb.extend((json.len() as u32).to_le_bytes());
        glb.extend(0x4E4F_534Au32.to_le_bytes());
        glb.extend(json);
        assert_eq!(json_of(&glb), Ok(&json[..]));
        let mut short = glb.clone();
        short[8..12].copy_from_slice(&3u32.to_le_bytes());
        assert!(json_of(&short).is_err(), "a length under the header");
        let mut long = glb.clone();
        long[12..16].copy_from_slice(&999u32.to_le_bytes());
        assert!(json_of(&long).is_err(), "a chunk past the container");
        assert!(json_of(&glb[..10]).is_err(), "a cut header");
    }
}

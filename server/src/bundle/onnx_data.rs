//! Whether an ONNX graph keeps tensor data in external files (`weights.bin` beside the graph).
//!
//! Such bundles are refused. ONNX Runtime memory-maps external data: a file truncated under a
//! served model kills the process with SIGBUS at the next run that touches it; and the
//! manifest's sha256 covers the graph file only, so two bundles whose external files differ
//! would render differently under one model id. A graph that holds its weights is read whole
//! into memory, hashed and handed to ONNX Runtime from there (`backend::ort`).
//!
//! Only the fields on the way to a tensor are decoded (prost skips the rest, weights included):
//! initializers, sparse initializers, and tensors in node attributes, at any depth of
//! subgraphs (`Loop`, `If`, `Scan` bodies) and functions.

use prost::Message;

#[derive(Clone, PartialEq, Message)]
struct ModelProto {
    #[prost(message, optional, tag = "7")]
    graph: Option<GraphProto>,
    #[prost(message, repeated, tag = "25")]
    functions: Vec<FunctionProto>,
}

#[derive(Clone, PartialEq, Message)]
struct FunctionProto {
    #[prost(message, repeated, tag = "7")]
    node: Vec<NodeProto>,
}

#[derive(Clone, PartialEq, Message)]
struct GraphProto {
    #[prost(message, repeated, tag = "1")]
    node: Vec<NodeProto>,
    #[prost(message, repeated, tag = "5")]
    initializer: Vec<TensorProto>,
    #[prost(message, repeated, tag = "15")]
    sparse_initializer: Vec<SparseTensorProto>,
}

#[derive(Clone, PartialEq, Message)]
struct NodeProto {
    #[prost(message, repeated, tag = "5")]
    attribute: Vec<AttributeProto>,
}

#[derive(Clone, PartialEq, Message)]
struct AttributeProto {
    #[prost(message, optional, tag = "5")]
    t: Option<TensorProto>,
    #[prost(message, optional, boxed, tag = "6")]
    g: Option<Box<GraphProto>>,
    #[prost(message, repeated, tag = "9")]
    tensors: Vec<TensorProto>,
    #[prost(message, repeated, tag = "10")]
    graphs: Vec<GraphProto>,
    #[prost(message, optional, tag = "22")]
    sparse_tensor: Option<SparseTensorProto>,
    #[prost(message, repeated, tag = "23")]
    sparse_tensors: Vec<SparseTensorProto>,
}

#[derive(Clone, PartialEq, Message)]
struct SparseTensorProto {
    #[prost(message, optional, tag = "1")]
    values: Option<TensorProto>,
    #[prost(message, optional, tag = "2")]
    indices: Option<TensorProto>,
}

#[derive(Clone, PartialEq, Message)]
struct TensorProto {
    #[prost(string, tag = "8")]
    name: String,
    #[prost(message, repeated, tag = "13")]
    external_data: Vec<StringStringEntryProto>,
    /// `DataLocation`: 0 default (in the graph), 1 external.
    #[prost(int32, tag = "14")]
    data_location: i32,
}

#[derive(Clone, PartialEq, Message)]
struct StringStringEntryProto {
    #[prost(string, tag = "1")]
    key: String,
    #[prost(string, tag = "2")]
    value: String,
}

/// `Err` naming the first tensor of `graph` (an ONNX model's bytes) whose data lies in an
/// external file, or saying that the bytes are not an ONNX model.
pub fn refuse_external_data(graph: &[u8]) -> Result<(), String> {
    let model = ModelProto::decode(graph).map_err(|e| format!("not an ONNX model: {e}"))?;
    let in_functions = || model.functions.iter().flat_map(|f| &f.node).find_map(external_in_node);
    match model.graph.iter().find_map(external_in_graph).or_else(in_functions) {
        None => Ok(()),
        Some(t) => {
            let location = t.external_data.iter().find(|e| e.key == "location").map_or("", |e| e.value.as_str());
            Err(format!(
                "tensor \"{}\" keeps its data in an external file (\"{location}\"): a bundle's graphs must hold \
                 their weights (export without external data)",
                t.name
            ))
        }
    }
}

fn external_in_graph(graph: &GraphProto) -> Option<&TensorProto> {
    let sparse = graph.sparse_initializer.iter().flat_map(sparse_parts);
    graph
        .initializer
        .iter()
        .chain(sparse)
        .find(|t| is_external(t))
        .or_else(|| graph.node.iter().find_map(external_in_node))
}

fn external_in_node(node: &NodeProto) -> Option<&TensorProto> {
    node.attribute.iter().find_map(|a| {
        let sparse = a.sparse_tensor.iter().chain(&a.sparse_tensors).flat_map(sparse_parts);
        let tensors = a.t.iter().chain(&a.tensors).chain(sparse);
        tensors
            .into_iter()
            .find(|t| is_external(t))
            .or_else(|| a.g.iter().map(|g| &**g).chain(&a.graphs).find_map(external_in_graph))
    })
}

fn sparse_parts(s: &SparseTensorProto) -> impl Iterator<Item = &TensorProto> {
    s.values.iter().chain(s.indices.iter())
}

fn is_external(t: &TensorProto) -> bool {
    t.data_location == 1 || !t.external_data.is_empty()
}

#[cfg(test)]
pub(super) mod tests {
    use super::*;

    /// The bytes of a model whose graph has one initializer, `name`, in `weights.bin`.
    pub fn model_with_external_tensor(name: &str) -> Vec<u8> {
        model(GraphProto { initializer: vec![external(name)], ..Default::default() })
    }

    fn external(name: &str) -> TensorProto {
        let location = StringStringEntryProto { key: "location".into(), value: "weights.bin".into() };
        TensorProto { name: name.into(), external_data: vec![location], data_location: 1 }
    }

    fn inline(name: &str) -> TensorProto {
        TensorProto { name: name.into(), ..Default::default() }
    }

    fn model(graph: GraphProto) -> Vec<u8> {
        ModelProto { graph: Some(graph), functions: vec![] }.encode_to_vec()
    }

    #[test]
    fn finds_external_data_in_initializers_and_loop_bodies() {
        let plain = GraphProto { initializer: vec![inline("w")], ..Default::default() };
        assert_eq!(refuse_external_data(&model(plain.clone())), Ok(()));

        let top = GraphProto { initializer: vec![inline("a"), external("w")], ..Default::default() };
        let e = refuse_external_data(&model(top)).unwrap_err();
        assert!(e.contains("tensor \"w\"") && e.contains("weights.bin"), "{e}");

        // A Loop whose body holds a Constant with external data.
        let constant = NodeProto { attribute: vec![AttributeProto { t: Some(external("c")), ..Default::default() }] };
        let body = GraphProto { node: vec![constant], ..Default::default() };
        let looped = NodeProto { attribute: vec![AttributeProto { g: Some(Box::new(body)), ..Default::default() }] };
        let outer = GraphProto { node: vec![looped], ..plain };
        assert!(refuse_external_data(&model(outer)).unwrap_err().contains("tensor \"c\""));

        let sparse = SparseTensorProto { values: Some(external("s")), indices: Some(inline("i")) };
        let graph = GraphProto { sparse_initializer: vec![sparse], ..Default::default() };
        assert!(refuse_external_data(&model(graph)).unwrap_err().contains("tensor \"s\""));
    }

    #[test]
    fn the_committed_bundles_hold_their_weights() {
        let root = concat!(env!("CARGO_MANIFEST_DIR"), "/..");
        for dir in ["bundles/default", "tests/fixtures/parity/bundle"] {
            for entry in std::fs::read_dir(format!("{root}/{dir}")).unwrap() {
                let path = entry.unwrap().path();
                if path.extension().is_some_and(|e| e == "onnx") {
                    let bytes = std::fs::read(&path).unwrap();
                    assert_eq!(refuse_external_data(&bytes), Ok(()), "{}", path.display());
                }
            }
        }
        assert!(refuse_external_data(b"stand-in").unwrap_err().starts_with("not an ONNX model"));
    }
}

//! Prints the OpenAPI document that the server serves at `/openapi.json`. It is committed as
//! docs/openapi.json (a test fails when the two differ); regenerate it with
//! `cargo run -q -p scnerf-server --example openapi > docs/openapi.json`.

fn main() {
    let document = scnerf_server::http::openapi::document();
    println!("{}", serde_json::to_string_pretty(&document).expect("a JSON value serialises"));
}

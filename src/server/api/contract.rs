//! What the OpenAPI description says of every route that the handlers'
//! annotations need not repeat: the error answers that the shared
//! extractors and the token check give (so a client, or a fuzzer, finds
//! every status it can get in the spec), and the links between operations
//! (so a stateful client learns that the `id` from `POST /runs` is what
//! `/runs/{id}/…` takes).

use std::collections::BTreeMap;

use utoipa::openapi::link::LinkBuilder;
use utoipa::openapi::path::{Operation, ParameterIn, PathItem};
use utoipa::openapi::{ContentBuilder, OpenApi, Ref, RefOr, Response, ResponseBuilder};

/// The standard error answers and the links, added to the description.
pub struct Contract;

impl utoipa::Modify for Contract {
    fn modify(&self, openapi: &mut OpenApi) {
        for item in openapi.paths.paths.values_mut() {
            for (_, op) in operations_mut(item) {
                add_standard_answers(op);
            }
        }
        add_links(openapi);
    }
}

/// The operations of a path, by method.
fn operations_mut(item: &mut PathItem) -> impl Iterator<Item = (&'static str, &mut Operation)> {
    [
        ("get", item.get.as_mut()),
        ("put", item.put.as_mut()),
        ("post", item.post.as_mut()),
        ("delete", item.delete.as_mut()),
        ("patch", item.patch.as_mut()),
        ("head", item.head.as_mut()),
        ("options", item.options.as_mut()),
    ]
    .into_iter()
    .filter_map(|(method, op)| op.map(|op| (method, op)))
}

fn error_answer(description: &str) -> RefOr<Response> {
    RefOr::T(
        ResponseBuilder::new()
            .description(description)
            .content(
                "application/json",
                ContentBuilder::new()
                    .schema(Some(Ref::from_schema_name("ErrorBody")))
                    .build(),
            )
            .build(),
    )
}

/// Adds the answers that come from the shared machinery rather than the
/// handler: the JSON body extractor (`ApiJson`), the query and path
/// extractors (`ApiQuery`, `ApiPath`) and the token check. A status the
/// handler documents itself keeps its own description.
fn add_standard_answers(op: &mut Operation) {
    let takes = |place: ParameterIn| {
        op.parameters
            .iter()
            .flatten()
            .any(|p| p.parameter_in == place)
    };
    let (in_query, in_path) = (takes(ParameterIn::Query), takes(ParameterIn::Path));
    let secured = op.security.as_ref().is_some_and(|s| !s.is_empty());
    let has_body = op.request_body.is_some();
    let mut add = |status: &str, description: &str| {
        op.responses
            .responses
            .entry(status.to_string())
            .or_insert_with(|| error_answer(description));
    };
    if has_body {
        add("400", "Malformed JSON");
        add("413", "Body over 64 KiB");
        add(
            "415",
            "Not `Content-Type: application/json`, or no body at all",
        );
        add(
            "422",
            "The JSON reads but a field is missing, unknown or unusable",
        );
    }
    if in_query {
        add("400", "A malformed query (a value of the wrong type)");
    }
    if in_path {
        add("400", "A path segment that cannot be read");
        add("404", "Nothing by that name");
    }
    if secured {
        add("401", "Missing or wrong token");
    }
}

/// Where a value for a link's parameter comes from, and which operations
/// take it as their path parameter `param`.
struct LinkSource {
    /// operationId of the operation whose answer gives the value.
    from: &'static str,
    /// The answers' statuses.
    statuses: &'static [&'static str],
    /// A runtime expression for the value.
    value: &'static str,
    /// Paths under this prefix take it.
    prefix: &'static str,
    /// The path parameter it fills.
    param: &'static str,
}

const LINK_SOURCES: &[LinkSource] = &[
    LinkSource {
        from: "create_run",
        statuses: &["201"],
        value: "$response.body#/id",
        prefix: "/api/v1/runs/{id}",
        param: "id",
    },
    LinkSource {
        from: "list_runs",
        statuses: &["200"],
        value: "$response.body#/runs/0/id",
        prefix: "/api/v1/runs/{id}",
        param: "id",
    },
    LinkSource {
        from: "submit",
        statuses: &["200", "202"],
        value: "$request.path.id",
        prefix: "/api/v1/runs/{id}/process",
        param: "id",
    },
    LinkSource {
        from: "list_peers",
        statuses: &["200"],
        value: "$response.body#/peers/1/name",
        prefix: "/api/v1/peers/{name}",
        param: "name",
    },
    LinkSource {
        from: "post_queue",
        statuses: &["201"],
        value: "$response.body#/item/id",
        prefix: "/api/v1/queue/{item}",
        param: "item",
    },
    LinkSource {
        from: "get_queue",
        statuses: &["200"],
        value: "$response.body#/items/0/id",
        prefix: "/api/v1/queue/{item}",
        param: "item",
    },
    LinkSource {
        from: "plans",
        statuses: &["200"],
        value: "$response.body#/plans/0/name",
        prefix: "/api/v1/plans/{name}",
        param: "name",
    },
];

/// Adds an OpenAPI link from each [`LINK_SOURCES`] answer to every
/// operation under its prefix, named by the target's operationId.
fn add_links(openapi: &mut OpenApi) {
    // (operationId, path) of every operation, to find the targets.
    let mut targets: Vec<(String, String)> = Vec::new();
    for (path, item) in openapi.paths.paths.iter_mut() {
        for (_, op) in operations_mut(item) {
            if let Some(id) = &op.operation_id {
                targets.push((id.clone(), path.clone()));
            }
        }
    }
    for item in openapi.paths.paths.values_mut() {
        for (_, op) in operations_mut(item) {
            let Some(from) = op.operation_id.clone() else {
                continue;
            };
            for source in LINK_SOURCES.iter().filter(|s| s.from == from) {
                let links: BTreeMap<_, _> = targets
                    .iter()
                    .filter(|(id, path)| *id != from && path.starts_with(source.prefix))
                    .map(|(id, _)| {
                        let link = LinkBuilder::new()
                            .operation_id(id.clone())
                            .parameter(source.param, source.value)
                            .build();
                        (id.clone(), RefOr::T(link))
                    })
                    .collect();
                for status in source.statuses {
                    if let Some(RefOr::T(answer)) = op.responses.responses.get_mut(*status) {
                        answer.links.extend(links.clone());
                    }
                }
            }
        }
    }
}

/// The description as served. utoipa (5.5) writes a link's `operationId`,
/// `operationRef` and `requestBody` in snake case, which no OpenAPI tool
/// reads: they are renamed here.
pub fn served(openapi: &OpenApi) -> serde_json::Value {
    let mut spec = serde_json::to_value(openapi).unwrap_or_default();
    let answers = spec["paths"]
        .as_object_mut()
        .into_iter()
        .flat_map(|paths| paths.values_mut())
        .filter_map(serde_json::Value::as_object_mut)
        .flat_map(|item| item.values_mut())
        .filter_map(|op| op.get_mut("responses").and_then(|r| r.as_object_mut()))
        .flat_map(|responses| responses.values_mut());
    for answer in answers {
        let Some(links) = answer.get_mut("links").and_then(|l| l.as_object_mut()) else {
            continue;
        };
        for link in links
            .values_mut()
            .filter_map(serde_json::Value::as_object_mut)
        {
            for (snake, camel) in [
                ("operation_id", "operationId"),
                ("operation_ref", "operationRef"),
                ("request_body", "requestBody"),
            ] {
                if let Some(value) = link.remove(snake) {
                    link.insert(camel.to_string(), value);
                }
            }
        }
    }
    spec
}

#[cfg(test)]
mod tests {
    use super::*;

    fn spec() -> serde_json::Value {
        served(&super::super::openapi())
    }

    #[test]
    fn every_json_body_documents_the_extractors_answers() {
        let spec = spec();
        let paths = spec["paths"].as_object().cloned().unwrap_or_default();
        let mut checked = 0;
        for (path, item) in &paths {
            for (method, op) in item.as_object().into_iter().flatten() {
                if op.get("requestBody").is_some() {
                    for status in ["400", "413", "415", "422"] {
                        assert!(
                            op["responses"].get(status).is_some(),
                            "{method} {path} lacks {status}"
                        );
                    }
                    checked += 1;
                }
                if op["security"].as_array().is_some_and(|s| !s.is_empty()) {
                    assert!(
                        op["responses"].get("401").is_some(),
                        "{method} {path} lacks 401"
                    );
                }
            }
        }
        // The five manual-control routes, runs, queue, process, trade-off.
        assert!(checked >= 9, "only {checked} operations take a body");
    }

    #[test]
    fn a_new_run_links_to_every_route_of_a_run() {
        let spec = spec();
        let links = &spec["paths"]["/api/v1/runs"]["post"]["responses"]["201"]["links"];
        let names: Vec<&String> = links
            .as_object()
            .map(|l| l.keys().collect())
            .unwrap_or_default();
        for target in [
            "get_run",
            "run_steps",
            "frame_raw",
            "btf_data",
            "submit",
            "get_job",
        ] {
            assert!(
                names.iter().any(|n| *n == target),
                "{target} not in {names:?}"
            );
        }
        assert_eq!(links["get_run"]["parameters"]["id"], "$response.body#/id");
        assert_eq!(links["get_run"]["operationId"], "get_run");
        // The peers' routes take a name from the peer list.
        let peers = &spec["paths"]["/api/v1/peers"]["get"]["responses"]["200"]["links"];
        assert!(peers.get("pause_peer").is_some(), "{peers}");
    }

    #[test]
    fn query_structs_are_query_parameters() {
        let spec = spec();
        for (path, name) in [
            ("/api/v1/runs/{id}/btf", "components"),
            ("/api/v1/runs/{id}/btf/mesh/{kind}", "density"),
        ] {
            let params = spec["paths"][path]["get"]["parameters"]
                .as_array()
                .cloned()
                .unwrap_or_default();
            let p = params.iter().find(|p| p["name"] == name);
            assert_eq!(
                p.map(|p| p["in"].clone()),
                Some("query".into()),
                "{path} {name}"
            );
        }
    }
}

//! Replays every ```transcript block of `firmware-protocols/robot-arm.md`
//! against the simulated controller (the test is the host) and against the
//! driver (the test is the device), so spec, simulator and driver cannot
//! drift apart.

use std::sync::Arc;

use rigd::model::profile::{Limits, Motion};
use rigd::rig::drivers::acl::{AclArm, AclConfig, AclJointConfig};
use rigd::rig::hal::{Arm, DeviceError};
use rigd_core::Clock;
use rigd_proto::acl::LineSplitter;
use rigd_sim::firmware::acl::{serve, AclParams};
use rigd_sim::{FaultInjector, FaultRule};
use tokio::io::{AsyncReadExt, AsyncWriteExt, DuplexStream};

#[derive(Debug, Clone)]
enum Step {
    Send(String),
    Recv(String),
    Call(String, Vec<f64>),
    Expect(String),
    Sleep(f64),
    Fault(String),
}

fn parse_step(line: &str) -> Step {
    if let Some(x) = line.strip_prefix("> ") {
        Step::Send(x.to_string())
    } else if let Some(x) = line.strip_prefix("< ") {
        Step::Recv(x.to_string())
    } else if let Some(x) = line.strip_prefix("@ call ") {
        let mut it = x.split_whitespace();
        let op = it.next().unwrap_or_default().to_string();
        Step::Call(op, it.map(|v| v.parse().expect("number")).collect())
    } else if let Some(x) = line.strip_prefix("@ expect ") {
        Step::Expect(x.to_string())
    } else if let Some(x) = line.strip_prefix("@ sleep ") {
        Step::Sleep(x.trim().parse().expect("sleep seconds"))
    } else if let Some(x) = line.strip_prefix("@ fault ") {
        Step::Fault(x.to_string())
    } else {
        panic!("bad transcript line `{line}`")
    }
}

fn transcripts() -> Vec<Vec<Step>> {
    let path = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/firmware-protocols/robot-arm.md"
    );
    let text = std::fs::read_to_string(path).expect("read robot-arm.md");
    let mut out = Vec::new();
    let mut current: Option<Vec<Step>> = None;
    for line in text.lines() {
        if let Some(steps) = current.as_mut() {
            if line.trim() == "```" {
                out.push(current.take().expect("block"));
            } else if !line.starts_with('#') && !line.trim().is_empty() {
                steps.push(parse_step(line));
            }
        } else if line.trim() == "```transcript" {
            current = Some(Vec::new());
        }
    }
    out
}

struct Reader {
    split: LineSplitter,
    lines: std::collections::VecDeque<String>,
}

impl Reader {
    fn new() -> Reader {
        Reader {
            split: LineSplitter::new(256),
            lines: Default::default(),
        }
    }
    async fn line(&mut self, s: &mut DuplexStream) -> String {
        loop {
            if let Some(l) = self.lines.pop_front() {
                return l;
            }
            let mut b = [0u8; 256];
            let n = s.read(&mut b).await.expect("read");
            assert!(n > 0, "unexpected EOF");
            for &x in &b[..n] {
                if let Some(l) = self.split.push(x) {
                    self.lines.push_back(l.text);
                }
            }
        }
    }
}

#[test]
fn spec_has_at_least_three_transcripts() {
    assert!(transcripts().len() >= 3);
}

#[tokio::test(start_paused = true)]
async fn transcripts_replay_against_the_simulator() {
    for (i, steps) in transcripts().into_iter().enumerate() {
        let clock = Clock::virtual_time();
        let rules: Vec<FaultRule> = steps
            .iter()
            .filter_map(|s| match s {
                Step::Fault(r) => Some(r.parse().expect("rule")),
                _ => None,
            })
            .collect();
        let (mut host, dev) = tokio::io::duplex(4096);
        tokio::spawn(serve(
            dev,
            AclParams::default(),
            clock.clone(),
            Arc::new(FaultInjector::new(rules)),
        ));
        let mut rd = Reader::new();
        for s in &steps {
            match s {
                Step::Send(l) => {
                    host.write_all(format!("{l}\r").as_bytes())
                        .await
                        .expect("write");
                }
                Step::Recv(l) => {
                    let got = rd.line(&mut host).await;
                    assert_eq!(&got, l, "transcript {i}");
                }
                Step::Sleep(s) => clock.sleep_s(*s).await,
                _ => {}
            }
        }
    }
}

pub fn wrist() -> Vec<AclJointConfig> {
    let p = AclParams::default();
    ["roll", "pitch", "twist"]
        .iter()
        .zip(&p.joints)
        .map(|(n, j)| AclJointConfig {
            name: n.to_string(),
            limits: Limits {
                min: j.min_deg,
                max: j.max_deg,
            },
            motion: Motion {
                max_velocity: j.motion.max_velocity,
                acceleration: j.motion.acceleration,
                settle_s: j.motion.settle_s,
            },
            counts_per_deg: j.counts_per_deg,
            home_deg: 0.0,
        })
        .collect()
}

fn check(expect: &str, r: Result<Vec<f64>, DeviceError>, i: usize) {
    let mut w = expect.split_whitespace();
    let kind = w.next().expect("kind");
    if kind == "ok" {
        let got = r.unwrap_or_else(|e| panic!("transcript {i}: {e}"));
        let want: Vec<f64> = w.map(|v| v.parse().expect("num")).collect();
        assert_eq!(got.len(), want.len(), "transcript {i}");
        for (g, x) in got.iter().zip(&want) {
            assert!((g - x).abs() < 1e-3, "transcript {i}: {got:?} vs {want:?}");
        }
    } else {
        let e = r.expect_err("expected an error");
        let k = serde_json::to_value(e.kind).expect("json");
        assert_eq!(k.as_str(), Some(kind), "transcript {i}: {e}");
        let text: Vec<&str> = w.collect();
        assert!(e.message.contains(&text.join(" ")), "transcript {i}: {e}");
    }
}

#[tokio::test(start_paused = true)]
async fn transcripts_replay_against_the_driver() {
    for (i, steps) in transcripts().into_iter().enumerate() {
        let (host, mut dev) = tokio::io::duplex(4096);
        let device: Vec<Step> = steps
            .iter()
            .filter(|s| matches!(s, Step::Send(_) | Step::Recv(_)))
            .cloned()
            .collect();
        let dev_task = tokio::spawn(async move {
            let mut rd = Reader::new();
            for s in device {
                match s {
                    Step::Send(l) => assert_eq!(rd.line(&mut dev).await, l),
                    Step::Recv(l) => dev
                        .write_all(format!("{l}\r\n").as_bytes())
                        .await
                        .expect("write"),
                    _ => {}
                }
            }
            dev
        });
        let clock = Clock::virtual_time();
        let cfg = AclConfig::new("arm", wrist());
        let mut host = Some(host);
        let mut arm: Option<AclArm<DuplexStream>> = None;
        let mut last: Option<Result<Vec<f64>, DeviceError>> = None;
        for s in &steps {
            match s {
                Step::Call(op, args) => {
                    let r = match op.as_str() {
                        "connect" => {
                            match AclArm::connect(
                                host.take().expect("one connect"),
                                cfg.clone(),
                                clock.clone(),
                            )
                            .await
                            {
                                Ok(a) => {
                                    let j = a.last_joints().map(<[f64]>::to_vec);
                                    arm = Some(a);
                                    Ok(j.expect("joints"))
                                }
                                Err(e) => Err(e),
                            }
                        }
                        "home" => arm.as_mut().expect("arm").home().await,
                        "move" => arm.as_mut().expect("arm").move_joints(args).await,
                        "joints" => arm.as_mut().expect("arm").joints().await,
                        "abort" => arm.as_mut().expect("arm").abort().await,
                        o => panic!("unknown op {o}"),
                    };
                    last = Some(r);
                }
                Step::Expect(x) => check(x, last.take().expect("a call before expect"), i),
                _ => {}
            }
        }
        dev_task.await.expect("device script completed");
    }
}

#include "records/record_writer.hpp"

#include <cstdio>
#include <filesystem>

#include "common/error.hpp"

namespace posecal {

namespace fs = std::filesystem;

namespace {

// Seconds between tries of a store that failed (the finish always tries).
constexpr std::chrono::seconds kRetryAfter{5};

// The spool files of one store share a prefix: FNV-1a of its location, in hex (stable across
// builds, and it does not put a URL's password into a file name).
std::string store_key(const std::string& location) {
  unsigned long long h = 1469598103934665603ULL;
  for (unsigned char ch : location) {
    h ^= ch;
    h *= 1099511628211ULL;
  }
  char buf[17];
  std::snprintf(buf, sizeof buf, "%016llx", h);
  return buf;
}

}  // namespace

struct RecordWriter::Part {
  enum Kind { kEngine, kKeyframe, kFinish } kind;
  cv::Size size;
  std::map<std::string, std::string> locked;
  StoredKeyframe keyframe;
  std::string state, result, verdict;
  std::optional<double> expected;

  void write(RecordStore& s, const std::string& run_id) const {
    switch (kind) {
      case kEngine:
        s.set_engine(run_id, size, locked);
        break;
      case kKeyframe:
        s.add_keyframe(run_id, keyframe);
        break;
      case kFinish:
        s.finish_run(run_id, state, result, verdict, expected);
        break;
    }
  }
};

RecordWriter::RecordWriter(std::string location, RunIdentity identity, std::string spool_dir)
    : location_(std::move(location)),
      spool_dir_(std::move(spool_dir)),
      identity_(std::move(identity)) {
  if (!spool_dir_.empty()) {
    try {
      replay_spool(location_, spool_dir_);
    } catch (const std::exception&) {
      // The store is away: the spool waits for a later writer; this run's note says so below.
    }
  }
  flush();
}

RecordWriter::~RecordWriter() = default;

void RecordWriter::set_engine(cv::Size image_size,
                              const std::map<std::string, std::string>& locked) {
  auto p = std::make_unique<Part>();
  p->kind = Part::kEngine;
  p->size = image_size;
  p->locked = locked;
  queue_.push_back(std::move(p));
  flush();
}

void RecordWriter::add_keyframe(StoredKeyframe keyframe) {
  auto p = std::make_unique<Part>();
  p->kind = Part::kKeyframe;
  p->keyframe = std::move(keyframe);
  queue_.push_back(std::move(p));
  flush();
}

void RecordWriter::finish(const std::string& state, const std::string& result_json,
                          const std::string& verdict, std::optional<double> expected_error_px) {
  auto p = std::make_unique<Part>();
  p->kind = Part::kFinish;
  p->state = state;
  p->result = result_json;
  p->verdict = verdict;
  p->expected = expected_error_px;
  queue_.push_back(std::move(p));
  next_try_ = {};  // the last chance before the spool
  if (!flush()) spool();
}

bool RecordWriter::flush() {
  if (refused_) return false;
  if (pending() == 0) return true;
  if (std::chrono::steady_clock::now() < next_try_) return false;
  try {
    if (!store_) store_ = RecordStore::open(location_);
    if (!begun_) {
      store_->begin_run(identity_);
      begun_ = true;
    }
    while (!queue_.empty()) {
      queue_.front()->write(*store_, identity_.run_id);
      queue_.erase(queue_.begin());
    }
    note_.clear();
    return true;
  } catch (const Error& e) {
    store_.reset();  // a new connection next time
    if (!begun_ && e.code() != ErrorCode::kIo) {
      // Not the store being away: the run id is taken, or the store is of a newer posecal.
      // Writing again will not help.
      refused_ = true;
      queue_.clear();
      note_ = std::string("not recorded: ") + e.what();
      return false;
    }
    next_try_ = std::chrono::steady_clock::now() + kRetryAfter;
    note_ = "the store is away (" + std::to_string(pending()) +
            " part(s) of the record kept to write when it is back): " + e.what();
    return false;
  } catch (const std::exception& e) {
    store_.reset();
    next_try_ = std::chrono::steady_clock::now() + kRetryAfter;
    note_ = std::string("the record is behind: ") + e.what();
    return false;
  }
}

void RecordWriter::spool() {
  if (refused_ || pending() == 0) return;
  const std::string why = note_;
  if (spool_dir_.empty()) {
    note_ = why + "; no spool directory: the record is incomplete";
    return;
  }
  const fs::path final_path =
      fs::path(spool_dir_) / (store_key(location_) + "-" + identity_.run_id + ".sqlite");
  const fs::path part_path = final_path.string() + ".part";
  try {
    std::error_code ec;
    fs::create_directories(spool_dir_, ec);
    fs::remove(part_path, ec);
    {
      auto local = RecordStore::open(part_path.string());
      // The spool holds the whole run header even if the store has it: replay skips what the
      // store already holds.
      local->begin_run(identity_);
      for (const auto& p : queue_) p->write(*local, identity_.run_id);
    }
    fs::rename(part_path, final_path);
    spooled_ = final_path.string();
    note_ = why + "; spooled to " + spooled_ + ", replayed when a later run opens the store";
  } catch (const std::exception& e) {
    std::error_code ec;
    fs::remove(part_path, ec);
    note_ = why + "; the spool failed too: " + e.what();
  }
}

std::vector<std::string> RecordWriter::replay_spool(const std::string& location,
                                                    const std::string& spool_dir) {
  std::vector<std::string> replayed;
  const std::string prefix = store_key(location) + "-";
  std::vector<fs::path> files;
  std::error_code ec;
  for (const auto& e : fs::directory_iterator(spool_dir, ec)) {
    const std::string name = e.path().filename().string();
    if (name.rfind(prefix, 0) == 0 && e.path().extension() == ".sqlite") files.push_back(e.path());
  }
  if (files.empty()) return replayed;
  auto store = RecordStore::open(location);
  for (const fs::path& file : files) {
    RunRecord run;
    {
      auto local = RecordStore::open(file.string());
      const std::vector<RunSummary> runs = local->list_runs();
      if (runs.size() != 1) continue;  // not a spool file of ours: left alone
      run = local->get_run(runs[0].identity.run_id);
    }
    const std::string& id = run.summary.identity.run_id;
    bool known = true;
    try {
      store->get_run(id);
    } catch (const Error& e) {
      if (e.code() != ErrorCode::kNotFound) throw;
      known = false;
    }
    if (!known) store->begin_run(run.summary.identity);
    if (run.image_width > 0) {
      store->set_engine(id, cv::Size(run.image_width, run.image_height), run.locked_settings);
    }
    for (const StoredKeyframe& k : run.keyframes) store->add_keyframe(id, k);
    if (run.summary.state != "running") {
      store->finish_run(id, run.summary.state, run.result, run.summary.verdict,
                        run.summary.expected_error_px);
    }
    fs::remove(file, ec);
    fs::remove(file.string() + "-wal", ec);
    fs::remove(file.string() + "-shm", ec);
    replayed.push_back(id);
  }
  return replayed;
}

}  // namespace posecal

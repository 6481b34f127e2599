// One run's record, written as the session goes, that survives a store that goes away.
//
// Each part of the run (its beginning, the engine's image size and locked settings, each
// keyframe, the finish) is queued and written in order; what a store cannot take (a PostgreSQL
// server restarting, a network cut, a locked or full SQLite file) stays queued and is written at
// the next part or at the finish, over a new connection. If the store is still away when the run
// finishes, the queue is kept in a spool (a SQLite record store `<spool>/<run id>.sqlite`,
// written in full and then renamed into place) when a spool directory is given, and replayed
// into the store by the next writer that opens the same store with the same spool directory.
// Nothing here throws into the calibration: failures become the note.
#pragma once

#include <chrono>
#include <map>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "records/record_store.hpp"

namespace posecal {

class RecordWriter {
 public:
  // `spool_dir` may be empty (no spool: what the store never took is lost, and the note says
  // so). Replays the spool's earlier runs for this store first (see replay_spool).
  RecordWriter(std::string location, RunIdentity identity, std::string spool_dir);
  ~RecordWriter();
  RecordWriter(const RecordWriter&) = delete;
  RecordWriter& operator=(const RecordWriter&) = delete;

  void set_engine(cv::Size image_size, const std::map<std::string, std::string>& locked);
  void add_keyframe(StoredKeyframe keyframe);
  // The last part: written at once; what is still queued afterwards goes to the spool.
  void finish(const std::string& state, const std::string& result_json, const std::string& verdict,
              std::optional<double> expected_error_px);

  // Parts not yet in the store (0 when the record is complete so far).
  size_t pending() const { return queue_.size() + (begun_ ? 0 : 1); }
  // "" while every part is written; otherwise what went wrong and where the parts are.
  const std::string& note() const { return note_; }
  // The spool file holding the run when the store was away at the finish ("" if none).
  const std::string& spooled() const { return spooled_; }

  // Writes every spooled run of `spool_dir` that was recorded for `location` into it, and
  // removes each spool file once its run is in the store. Returns the run ids replayed; a run
  // the store already holds in full is not written twice. Throws Error(kIo) if the store
  // cannot be opened.
  static std::vector<std::string> replay_spool(const std::string& location,
                                               const std::string& spool_dir);

 private:
  struct Part;
  // Writes what is queued, in order; false (and the note) if the store failed.
  bool flush();
  void spool();

  std::string location_, spool_dir_, note_, spooled_;
  RunIdentity identity_;
  std::unique_ptr<RecordStore> store_;
  bool begun_ = false, refused_ = false;
  std::vector<std::unique_ptr<Part>> queue_;
  // After a failure the store is tried again at the next part, but not sooner than this (a
  // server that does not answer costs a connect timeout per try).
  std::chrono::steady_clock::time_point next_try_{};
};

}  // namespace posecal

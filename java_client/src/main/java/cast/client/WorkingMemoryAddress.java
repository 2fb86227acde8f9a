package cast.client;

/**
 * Where an entry lives: its id in the working memory of one subarchitecture.
 *
 * @param id the entry's id, unique within the SA's working memory
 * @param subarchitecture the SA whose working memory holds the entry
 */
public record WorkingMemoryAddress(String id, String subarchitecture) {
  @Override
  public String toString() {
    return subarchitecture + "/" + id;
  }
}
